"""The documentation: the paths the code and the docs name exist, the generated reference pages are
current, and the README keeps its promises (the two commands, its size, a container example whose
status page can be reached)."""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DOCS = ROOT.parent / "shared" / "docs"

#: a docs page or a test file as code, tests, tools and documents name it; ``shared/docs/...``
#: names the project's manuals beside the repository.
_DOC_PATH = re.compile(r"(?<![\w/.-])((?:shared/)?docs/[\w./-]+\.md|tests/[\w/]+\.py)")


def _tracked_text_files() -> list[Path]:
    listed = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    suffixes = {".py", ".md", ".toml", ".yml", ".yaml", ".sh", ".service", ""}
    return [ROOT / name for name in listed.splitlines() if Path(name).suffix in suffixes and (ROOT / name).is_file()]


def test_every_docs_and_test_path_named_in_the_repository_exists() -> None:
    """A note or a test moved or renamed leaves no reference to its old place behind (code comments,
    error messages, the Dockerfile, tests, tools, other pages)."""
    missing: list[str] = []
    for path in _tracked_text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for match in _DOC_PATH.finditer(text):
            named = match.group(1)
            if named.startswith("shared/"):
                if SHARED_DOCS.is_dir() and not (SHARED_DOCS / named.removeprefix("shared/docs/")).exists():
                    missing.append(f"{path.relative_to(ROOT)}: {named}")
            elif not (ROOT / named).exists():
                missing.append(f"{path.relative_to(ROOT)}: {named}")
    assert missing == []


def _tool(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"tools_{name}", ROOT / "tools" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_the_mutation_tool_finds_its_list_of_equivalent_mutants() -> None:
    """tools/mutation.py reads the equivalent mutants from the developers' note (a missing file
    would silently count none)."""
    mutation = _tool("mutation")
    assert mutation.EQUIVALENTS_DOC.exists()
    assert len(mutation.equivalent_mutants()) > 0


# --------------------------------------------------------------------------------------------
# The generated reference pages (tools/gen_reference.py)


def _generator() -> ModuleType:
    return _tool("gen_reference")


def test_the_generated_reference_pages_are_current() -> None:
    """docs/reference/config.md and cli.md are what the models and the parser give: after a key, a
    default, a limit, a description or an option changed, run ``python tools/gen_reference.py``."""
    generator = _generator()
    for path, render in generator.PAGES.items():
        assert path.read_text(encoding="utf-8") == render(), (
            f"{path.relative_to(ROOT)} is stale: run python tools/gen_reference.py"
        )


def test_a_changed_description_makes_the_config_page_stale(monkeypatch: pytest.MonkeyPatch) -> None:
    from gateway.config.schema import ModbusConfig

    generator = _generator()
    committed = generator.CONFIG_PAGE.read_text(encoding="utf-8")
    field = ModbusConfig.model_fields["idle_timeout"]
    monkeypatch.setattr(field, "description", "Close a silent connection after this many minutes.")
    page = generator.config_reference()
    assert page != committed
    assert "| `idle_timeout` | number (≥ 0) | `300.0` | Close a silent connection after this many minutes. |" in page
    assert generator.main(["--check"]) == 1


def test_the_check_passes_on_the_committed_pages(capsys: pytest.CaptureFixture[str]) -> None:
    assert _generator().main(["--check"]) == 0, capsys.readouterr().err


def test_every_config_key_has_a_description() -> None:
    """A key's description is the docstring under its field: a new key without one is not documented."""
    assert _generator().undocumented() == []


def test_the_config_page_lists_every_key_of_every_kind() -> None:
    generator = _generator()
    page = generator.CONFIG_PAGE.read_text(encoding="utf-8")
    missing = [
        f"{where}.{key}"
        for where, model in generator._models()
        for key, field in model.model_fields.items()
        if f"| `{key}` |" not in page and f".{key}]" not in page and f"`[{key}]`" not in page
        and f"`[[{key}]]`" not in page
    ]
    assert missing == []
    for table in ("`[modbus]`", "`[modbus.tls]`", "`[metrics]`", "`[logging]`", "`[[link.map]]`", "`[[link.file]]`"):
        assert f"## {table}" in page
    # a kind's own defaults, as its manual gives them (SLC 100/150: 9600 7E1, 0.3 s; DF1: 19200 8N1, 1 s)
    assert "| `baudrate` | integer | `9600` (slc-ascii), `19200` (df1) |" in page
    assert "`0.3` (slc-ascii), `1.0` (df1)" in page


# --------------------------------------------------------------------------------------------
# The README


def test_the_readme_keeps_the_two_commands_and_stays_short() -> None:
    """CI runs ``make test``; a fresh clone's reader runs ``make run``: the README's two commands.
    The rest of the documentation is the site; the README stays a page a person reads."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "make run     # " in readme and "make test    # " in readme
    assert len(readme.encode("utf-8")) <= 15 * 1024
    assert "make test" in (ROOT / ".ci" / "run").read_text(encoding="utf-8")


#: ``docker run`` options that take a value (the examples use these)
_DOCKER_VALUE_OPTIONS = {"--name", "--device", "-p", "--publish", "-v", "--volume", "--group-add", "-e", "--env"}


def _docker_run(text: str) -> list[str]:
    """The first ``docker run`` command of a Markdown text, its continuation lines joined, split."""
    block = text[text.index("docker run"):]
    lines: list[str] = []
    for line in block.splitlines():
        lines.append(line.rstrip().removesuffix("\\"))
        if not line.rstrip().endswith("\\"):
            break
    return shlex.split(" ".join(lines))


def _reachable_status_page(published: list[str], arguments: list[str]) -> None:
    """The status page the image serves with ``arguments`` listens on an address of the container
    that a published port reaches (not its loopback), on a port that is published."""
    from gateway.cli import build_parser

    parsed = build_parser().parse_args(arguments)
    assert parsed.command == "run"
    assert str(parsed.config) == "/etc/slc-gateway/gateway.toml"
    shipped = tomllib.loads((ROOT / "config" / "gateway.toml").read_text(encoding="utf-8"))
    listen = parsed.metrics_listen or shipped["metrics"]["listen"]
    host, _, port = listen.rpartition(":")
    assert host.strip("[]") in ("0.0.0.0", "::"), f"the status page listens on {listen}, the container's own"
    container_ports = {mapping.rsplit(":", 1)[-1] for mapping in published}
    assert port in container_ports, f"the status page's port {port} is not published ({published})"


def _run_example(text: str) -> tuple[list[str], list[str]]:
    """(published ports, the image's arguments) of a ``docker run`` example."""
    words = _docker_run(text)
    assert words[:2] == ["docker", "run"]
    published: list[str] = []
    index = 2
    while words[index].startswith("-"):
        if words[index] in _DOCKER_VALUE_OPTIONS:
            if words[index] in ("-p", "--publish"):
                published.append(words[index + 1])
            index += 2
        else:
            index += 1
    assert words[index] == "slc-gateway"  # the image
    return published, words[index + 1 :] or _image_command()


def _image_command() -> list[str]:
    """The Dockerfile's CMD: the image's arguments when ``docker run`` gives none."""
    command = re.search(r"^CMD (\[.*\])$", (ROOT / "Dockerfile").read_text(encoding="utf-8"), re.MULTILINE)
    assert command is not None
    return list(json.loads(command[1]))


def test_the_container_examples_publish_a_status_page_that_can_be_reached() -> None:
    """An example whose status page listens on 127.0.0.1 inside the container serves nobody."""
    for page in (ROOT / "README.md", ROOT / "docs" / "guide" / "deployment.md", ROOT / "Dockerfile"):
        published, arguments = _run_example(page.read_text(encoding="utf-8").replace("#   ", "").replace("#", ""))
        _reachable_status_page(published, arguments)


def test_the_compose_file_publishes_a_status_page_that_can_be_reached() -> None:
    text = (ROOT / "docker-compose.yml").read_text(encoding="utf-8")
    command = re.search(r"^\s+command: (\[.*\])$", text, re.MULTILINE)
    assert command is not None
    ports = re.findall(r'^\s+- "([\d.:]+)"', text, re.MULTILINE)
    _reachable_status_page(ports, json.loads(command[1]))


def test_the_status_block_page_lists_every_register() -> None:
    from gateway.modbus.mapping import STATUS_BASE, STATUS_REGISTERS

    page = (ROOT / "docs" / "reference" / "status-block.md").read_text(encoding="utf-8")
    address = STATUS_BASE
    for _name, width in STATUS_REGISTERS:
        cell = f"| {address} |" if width == 1 else f"| {address}\u2013{address + width - 1} |"
        assert cell in page
        address += width
    assert f"input registers {STATUS_BASE}-{address - 1}" in page
