"""The status page in a real headless Chromium (Debian's ``chromium`` + ``chromium-driver``, through selenium).

The demo gateway runs as a subprocess (``slc-gateway run``) with two more links on real ports: an SLC
150 served over TCP by ``slc-gateway simulate`` in its own process, which the test kills, and one on
a pseudo-terminal.  The page must list every link, with no error on a link that is up and never
failed (a port opens after the gateway starts) and the line's quality columns, show ages that move,
turn the killed link down within ``stale_after`` plus one poll period (plus the page's own
one-second refresh) and count its time down from then, show for unit 1 the values a Modbus read
gets, and say of the target unit (not polled) when its values go stale.
Screenshots (wide and phone-sized) are saved in the test's temporary directory; their paths are printed.

Without chromium, chromedriver or selenium the test is skipped naming what is missing, unless
``SLC_GATEWAY_REQUIRE_BROWSER=1`` (CI), which makes that a failure.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
from pymodbus.client import ModbusTcpClient

from tests.cli_support import start_simulator, stop
from tests.net import free_port
from tests.waiting import until_sync

ROOT = Path(__file__).resolve().parents[2]
HOST = "127.0.0.1"
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage")
STALE_AFTER = 2.0
FAST_INTERVAL = 0.5
PAGE_PERIOD = 1.0  # the page asks the API once a second (status.js PERIOD_MS)
NONE = "\u2013"  # an en dash: what the page shows for "none" (no error, not a thing of the protocol)
T = TypeVar("T")


def browser_or_skip() -> tuple[str, str]:
    """(chromium, chromedriver) paths; skip loudly naming what is missing (fail with SLC_GATEWAY_REQUIRE_BROWSER=1)."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    missing = [name for name, found in (("chromium (Debian package chromium)", chromium),
                                        ("chromedriver (Debian package chromium-driver)", driver),
                                        ("selenium (pip, the test extra)", importlib.util.find_spec("selenium")))
               if not found]
    if missing:
        message = f"headless browser test needs: {', '.join(missing)}"
        if os.environ.get("SLC_GATEWAY_REQUIRE_BROWSER") == "1":
            pytest.fail(message + " (SLC_GATEWAY_REQUIRE_BROWSER=1)")
        pytest.skip(message + "; set SLC_GATEWAY_REQUIRE_BROWSER=1 to fail instead")
    assert chromium is not None and driver is not None
    return chromium, driver


def wait_for(what: str, check: Callable[[], T | None], within: float) -> T:
    """Poll ``check`` until it returns something; fail naming ``what`` after ``within`` seconds."""
    return until_sync(check, within, step=0.1, what=what)


def api(port: int, path: str) -> Any:
    with urllib.request.urlopen(f"http://{HOST}:{port}{path}", timeout=5) as response:
        return json.loads(response.read())


@pytest.fixture
def plant(tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The demo gateway plus a link to an SLC 150 simulator in its own process, on free ports."""
    simulator, line = start_simulator("slc150", "--listen", f"{HOST}:0")
    found = re.search(r":(\d+) \(socket://", line)
    assert found is not None, line
    sim_port = int(found[1])
    on_pty, line = start_simulator("slc150", "--pty")
    pty = line.split(" on ")[-1]
    assert pty.startswith("/"), line
    modbus_port, http_port = free_port(), free_port()
    demo = (ROOT / "config" / "demo.toml").read_text(encoding="utf-8")
    demo = demo.replace('listen = "127.0.0.1:5020"', f'listen = "{HOST}:{modbus_port}"')
    demo = demo.replace('listen = "127.0.0.1:9108"', f'listen = "{HOST}:{http_port}"')
    demo += (f'\n[[link]]\nname = "press-remote"\nprotocol = "slc-ascii"\nport = "socket://{HOST}:{sim_port}"\n'
             f'unit = 7\nstale_after = {STALE_AFTER}\nfast_interval = {FAST_INTERVAL}\n'
             f'\n[[link]]\nname = "press-pty"\nprotocol = "slc-ascii"\nport = "{pty}"\nunit = 8\n')
    config = tmp_path / "plant.toml"
    config.write_text(demo, encoding="utf-8")
    log = (tmp_path / "gateway.log").open("w")
    gateway = subprocess.Popen([sys.executable, "-m", "gateway", "run", str(config)], stdout=log,
                               stderr=subprocess.STDOUT, cwd=tmp_path)
    try:
        names = re.findall(r'^name = "([^"]+)"', demo, re.MULTILINE)

        def all_up() -> bool:
            try:
                rows = api(http_port, "/api/status")["links"]
            except OSError:
                return False
            return [row["name"] for row in rows] == names and all(row["state"] == "up" for row in rows)

        wait_for("every link of the plant up", all_up, 30)
        yield {"names": names, "modbus": modbus_port, "http": http_port, "simulator": simulator, "tmp": tmp_path}
    finally:
        stop(simulator)
        stop(on_pty)
        gateway.terminate()
        try:
            gateway.wait(timeout=10)
        except subprocess.TimeoutExpired:
            gateway.kill()
            gateway.wait()
        log.close()


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[Any]:
    chromium, driver_path = browser_or_skip()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'chromium-profile'}", "--window-size=1360,1000"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(driver_path))
    try:
        yield driver
    finally:
        driver.quit()


# The page replaces its table bodies on every refresh: each table is read in one script, at once.
_ROWS_JS = """return Array.from(document.querySelectorAll(arguments[0] + ' tbody tr')).map(
    (row) => [row.dataset.link || row.dataset.address || '', row.className,
              Array.from(row.cells).map((cell) => cell.innerText)]);"""


def rows(browser: Any) -> dict[str, dict[str, str]]:
    """The links table as the user sees it: per link, its state class and the text of its cells."""
    return {key: {"state": state, "unit": cells[2], "age": cells[4]}
            for key, state, cells in browser.execute_script(_ROWS_JS, "#links")}


def columns(browser: Any) -> dict[str, dict[str, str]]:
    """Per link, the text of each cell under its column's heading (the first, State, under "State")."""
    heads = browser.execute_script(
        "return Array.from(document.querySelectorAll('#links thead th')).map((th) => th.textContent.trim());")
    return {key: dict(zip(heads, cells, strict=True)) for key, _, cells in browser.execute_script(_ROWS_JS, "#links")}


def register_rows(browser: Any) -> list[tuple[int, str, str, str]]:
    """(address, value, age, state) of the register view."""
    table = browser.execute_script(_ROWS_JS, "#registers")
    return [(int(key), cells[3], cells[4], cells[5]) for key, _, cells in table]


def show(browser: Any, unit: int, table: str, start: int, count: int) -> None:
    from selenium.webdriver.support.ui import Select

    Select(browser.find_element("id", "unit")).select_by_value(str(unit))
    Select(browser.find_element("id", "table")).select_by_value(table)
    for field, value in (("start", start), ("count", count)):
        box = browser.find_element("id", field)
        box.clear()
        box.send_keys(str(value))
    browser.find_element("css selector", "#view button").click()

    def shown() -> bool:
        addresses = [row[0] for row in register_rows(browser)]
        note = browser.find_element("id", "view-note").text
        return addresses == list(range(start, start + count)) and f"unit {unit} " in note

    wait_for(f"the register view of unit {unit} {table} {start}+{count}", shown, 10)


def test_status_page_in_chromium(plant: dict[str, Any], browser: Any) -> None:
    port = plant["http"]
    browser.get(f"http://{HOST}:{port}/")

    # Every link of the plant (the demo's and the remote one), each up.
    listed = wait_for("every link listed", lambda: (r := rows(browser)) and len(r) == len(plant["names"]) and r, 10)
    assert list(listed) == plant["names"]
    assert all(row["state"] == "up" for row in listed.values()), listed

    # The links on real ports (TCP, a pty) opened after the gateway started: up, no error, none shown.
    # Every link shows its line's quality; an SLC 100/150 has no NAK, a DF1 link no resync.
    table = columns(browser)
    for name in ("press-remote", "press-pty"):
        assert (table[name]["Errors"], table[name]["Last error"]) == ("0", NONE), table[name]
    for name, unit in (("press-pty", 8), ("slc504-sim", 3)):
        line = {key: table[name][key] for key in ("Check errors", "NAKs", "Timeouts", "Retransmits", "Resyncs")}
        print(f"unit {unit} line quality on the page: {line}")
        assert line["Check errors"].isdigit() and line["Timeouts"].isdigit() and line["Retransmits"].isdigit()
        assert (line["NAKs"] == NONE) == (name == "press-pty") and (line["Resyncs"] == NONE) == (name != "press-pty")

    # The register view of unit 1 shows what a Modbus read of the same range answers (presets of
    # 901-916: constant while nobody writes them).
    show(browser, 1, "holding", 32, 16)
    client = ModbusTcpClient(HOST, port=plant["modbus"], timeout=3, retries=0)
    assert client.connect()
    try:
        reply = client.read_holding_registers(32, count=16, device_id=1)
    finally:
        client.close()
    assert not reply.isError(), reply
    page = register_rows(browser)
    assert [value for _, value, _, _ in page] == [str(v) for v in reply.registers]
    assert {state for _, _, _, state in page} == {"FRESH"}

    # An age moves between two reads: the step counters are read every slow_interval (10 s), so
    # their age grows between two refreshes of the page.
    show(browser, 1, "input", 0, 8)
    first = register_rows(browser)[0][2]
    second = wait_for("an age that changes", lambda: (age := register_rows(browser)[0][2]) != first and age, 5)
    print(f"\nage of unit 1 input 0: {first!r}, then {second!r}")
    screenshot(browser, plant["tmp"], "status-page.png")

    # The remote controller's simulator stops: its row turns down.
    stopped = time.monotonic()
    stop(plant["simulator"])
    bound = STALE_AFTER + FAST_INTERVAL + PAGE_PERIOD
    wait_for("the stopped link shown down", lambda: rows(browser)["press-remote"]["state"] == "down", bound)
    print(f"press-remote shown down {time.monotonic() - stopped:.2f} s after its simulator stopped "
          f"(bound: stale_after {STALE_AFTER} + poll period {FAST_INTERVAL} + page refresh {PAGE_PERIOD})")
    # "for N s" counts from when it went down, not from when it came up (the plant has run for longer)
    down_for = columns(browser)["press-remote"]["State"].split("for ")[-1]
    assert down_for.endswith(" s") and float(down_for[:-2]) <= bound + PAGE_PERIOD, down_for
    assert all(row["state"] == "up" for name, row in rows(browser).items() if name != "press-remote")
    show(browser, 7, "holding", 32, 8)
    wait_for("the stopped link's values marked stale",
             lambda: {state for _, _, _, state in register_rows(browser)} == {"STALE"}, STALE_AFTER + PAGE_PERIOD + 1)
    screenshot(browser, plant["tmp"], "status-page-down.png")

    # The target unit is not polled: its note says when its values go stale (here: never).
    show(browser, 4, "holding", 0, 4)
    note = browser.find_element("id", "view-note").text
    assert "not polled" in note and "never go stale" in note and "never s" not in note, note
    browser.set_window_size(390, 844)  # a phone
    time.sleep(PAGE_PERIOD)
    screenshot(browser, plant["tmp"], "status-page-phone.png")
    assert browser.execute_script("return document.documentElement.scrollWidth") <= 390 + 1  # no sideways scroll


def screenshot(browser: Any, directory: Path, name: str) -> None:
    path = directory / name
    browser.save_screenshot(str(path))
    copy_to = os.environ.get("SLC_GATEWAY_SCREENSHOTS")
    if copy_to:
        Path(copy_to).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(copy_to) / name)
    print(f"screenshot: {path}")
