"""Every key a reload may see is either applied at once or reported as needing a restart (``gateway.reload``).

One table here says, for every key of the listener and log sections, a new value and whether the
running gateway takes it (``live``) or needs a restart; for a live key, what of the running
listeners shows it taken.  Three rules are held against the code:

* every key of those sections is in the table (a new key needs a decision);
* :func:`gateway.reload.restart_needed` names exactly the keys that are not live (a changed TLS
  listen address taken for live would report success while TLS clients still reach the old one);
* every key of :data:`gateway.reload.LIVE_KEYS` is applied by a reload of a gateway
  (``Gateway.apply``): a key added to ``LIVE_KEYS`` without its handler fails here.
"""

from __future__ import annotations

import logging
import shutil
import ssl
import subprocess
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from ipaddress import IPv4Network
from pathlib import Path

import pytest
from pydantic import BaseModel

from gateway import transport
from gateway.app import Gateway
from gateway.config import GatewayConfig, parse_config
from gateway.config.schema import LoggingConfig, MetricsConfig, ModbusConfig, TlsConfig
from gateway.modbus.server import ModbusTcpServer
from gateway.reload import LIVE_KEYS, restart_needed

SECTIONS: dict[str, type[BaseModel]] = {"modbus": ModbusConfig, "modbus.tls": TlsConfig, "metrics": MetricsConfig,
                                        "logging": LoggingConfig}


@dataclass(frozen=True)
class Change:
    """A key's new value (TOML, with ``{tls}`` for the certificates' folder), whether it is live, and
    for a live one what shows it applied (``seen(gateway)`` is the new value) and that value."""

    value: str
    live: bool
    seen: Callable[[Gateway], object] | None = None
    expected: object = None
    #: other keys of the section that change with it (a certificate with its key)
    also: tuple[tuple[str, str], ...] = ()


def plain(gateway: Gateway) -> ModbusTcpServer:
    return next(server for server in gateway.servers if server.ssl_context is None)


def tls(gateway: Gateway) -> ModbusTcpServer:
    return next(server for server in gateway.servers if server.ssl_context is not None)


def served_certificate(gateway: Gateway) -> str:
    """The subject common name of the certificate the TLS listener presents now (a handshake in memory)."""
    context = tls(gateway).ssl_context
    assert context is not None
    client_context = ssl.create_default_context()
    client_context.check_hostname = False
    client_context.verify_mode = ssl.CERT_NONE
    client_context.load_cert_chain(gateway.config.modbus.tls.cert.parent / "client.pem",  # type: ignore[union-attr]
                                   gateway.config.modbus.tls.cert.parent / "client.key")  # type: ignore[union-attr]
    c_in, c_out, s_in, s_out = ssl.MemoryBIO(), ssl.MemoryBIO(), ssl.MemoryBIO(), ssl.MemoryBIO()
    client = client_context.wrap_bio(c_in, c_out, server_side=False)
    server = context.wrap_bio(s_in, s_out, server_side=True)
    done = [False, False]
    for _ in range(20):
        for index, end in enumerate((client, server)):
            if not done[index]:
                try:
                    end.do_handshake()
                    done[index] = True
                except ssl.SSLWantReadError:
                    pass
        s_in.write(c_out.read())
        c_in.write(s_out.read())
        if all(done):
            break
    der = client.getpeercert(binary_form=True)
    assert der is not None
    pem = ssl.DER_cert_to_PEM_cert(der)
    for name in ("one", "two"):
        if (gateway.config.modbus.tls.cert.parent / f"{name}.pem").read_text() == pem:  # type: ignore[union-attr]
            return name
    return "another"


def ca_subject(gateway: Gateway) -> str:
    context = tls(gateway).ssl_context
    assert context is not None
    (ca,) = context.get_ca_certs()
    subject = ca["subject"]
    assert isinstance(subject, tuple)
    names = {str(pair[0][0]): str(pair[0][1]) for pair in subject}
    return names["commonName"]


#: section -> key -> its change; the values are not the defaults nor the base file's
TABLE: dict[str, dict[str, Change]] = {
    "modbus": {
        "listen": Change('"127.0.0.1:5999"', live=False),
        "max_connections": Change("7", True, lambda g: plain(g).admission.max_connections, 7),
        "max_connections_per_address": Change("3", True, lambda g: plain(g).admission.max_per_address, 3),
        "idle_timeout": Change("42.0", True, lambda g: plain(g).idle_timeout, 42.0),
        "frame_timeout": Change("2.5", True, lambda g: plain(g).frame_timeout, 2.5),
        "allow": Change('["10.0.0.0/8"]', True, lambda g: plain(g).admission.allow, (IPv4Network("10.0.0.0/8"),)),
        "loopback_reads": Change("false", True, lambda g: plain(g).admission.loopback_reads, False),
        "tls": Change("", live=False),  # a section of its own ([modbus.tls], below)
    },
    "modbus.tls": {
        "listen": Change('"127.0.0.1:5998"', live=False),
        "cert": Change('"{tls}/two.pem"', True, served_certificate, "two", also=(("key", '"{tls}/two.key"'),)),
        # the same certificate path, its file renewed, with a new key: the key is read again
        "key": Change('"{tls}/two.key"', True, served_certificate, "two", also=(("cert", '"{tls}/renewed.pem"'),)),
        "client_ca": Change('"{tls}/other-ca.pem"', True, ca_subject, "other CA"),
        "handshake_timeout": Change("9.0", True, lambda g: tls(g).handshake_timeout, 9.0),
        "max_handshakes": Change("5", True, lambda g: tls(g).admission.max_handshakes, 5),
        "roles": Change('{{ operator = "read-write", viewer = "read" }}', True,
                        lambda g: dict(tls(g).roles.roles) if tls(g).roles else None,  # type: ignore[union-attr]
                        {"operator": "read-write", "viewer": "read"}),
        "default_rights": Change('"read-write"', True,
                                 lambda g: tls(g).roles.default if tls(g).roles else None,  # type: ignore[union-attr]
                                 "read-write"),
    },
    "metrics": {
        "listen": Change('"127.0.0.1:5997"', live=False),
        "allow": Change('["192.168.0.0/16"]', True, lambda g: g.metrics.allow,  # type: ignore[union-attr]
                        (IPv4Network("192.168.0.0/16"),)),
        "max_connections": Change("11", True, lambda g: g.metrics.max_connections, 11),  # type: ignore[union-attr]
    },
    "logging": {
        "level": Change('"DEBUG"', True, lambda g: logging.getLogger().level, logging.DEBUG),
        "repeat_interval": Change("17.0", True, lambda g: plain(g).repeat_log.interval, 17.0),
        "trace_max_bytes": Change("123456", True, lambda g: transport._trace_max_bytes, 123456),
        "trace_backups": Change("7", True, lambda g: transport._trace_backups, 7),
    },
}

#: the file every change starts from: every section present (TOML values by section and key)
BASE: dict[str, dict[str, str]] = {
    "modbus": {"listen": '"127.0.0.1:0"'},
    "modbus.tls": {"listen": '"127.0.0.1:0"', "cert": '"{tls}/one.pem"', "key": '"{tls}/one.key"',
                   "client_ca": '"{tls}/ca.pem"', "roles": '{{ operator = "read" }}'},
    "metrics": {"listen": '"127.0.0.1:0"'},
    "logging": {"level": '"WARNING"'},
}

LINK = ('[[link]]\nname = "press"\nprotocol = "slc-ascii"\nport = "sim://slc150?ladder=0&instance={instance}"\n'
        "unit = 1\n")


def render(sections: dict[str, dict[str, str]], folder: Path) -> GatewayConfig:
    text = ""
    for section, keys in sections.items():
        text += f"[{section}]\n" + "".join(f"{key} = {value}\n" for key, value in keys.items()) + "\n"
    return parse_config(text.format(tls=folder) + LINK.format(instance=uuid.uuid4().hex))


def base_for(section: str, key: str) -> dict[str, dict[str, str]]:
    """The file a change of ``key`` starts from: for the TLS key, the certificate at the path it is
    renewed at (``renewed.pem``: the first certificate before, the second after)."""
    sections = {name: dict(keys) for name, keys in BASE.items()}
    if (section, key) == ("modbus.tls", "key"):
        sections[section]["cert"] = '"{tls}/renewed.pem"'
    return sections


def changed(section: str, key: str, folder: Path) -> GatewayConfig:
    change = TABLE[section][key]
    sections = base_for(section, key)
    sections[section][key] = change.value
    for other, value in change.also:
        sections[section][other] = value
    return render(sections, folder)


def renew(folder: Path, name: str) -> None:
    """The certificate file ``renewed.pem`` now holds certificate ``name``."""
    (folder / "renewed.pem").write_text((folder / f"{name}.pem").read_text())


def _openssl(folder: Path, *words: str) -> None:
    subprocess.run(["openssl", *words], cwd=folder, check=True, capture_output=True, timeout=30)


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two CAs; server certificates "one" and "two" and a client certificate, signed by the first."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not available")
    folder = tmp_path_factory.mktemp("tls")
    new_key = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    _openssl(folder, "req", "-x509", *new_key, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=CA")
    _openssl(folder, "req", "-x509", *new_key, "-keyout", "other-ca.key", "-out", "other-ca.pem", "-days", "2",
             "-subj", "/CN=other CA")
    for name in ("one", "two", "client"):
        _openssl(folder, "req", *new_key, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        _openssl(folder, "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                 "-CAcreateserial", "-days", "2", "-out", f"{name}.pem")
    return folder


@pytest.fixture(autouse=True)
def _keep_global_settings() -> Iterator[None]:
    """A reload sets the root logger's level and the trace limits: put them back."""
    level = logging.getLogger().level
    limits = transport._trace_max_bytes, transport._trace_backups
    yield
    logging.getLogger().setLevel(level)
    transport.set_trace_limits(*limits)


def test_every_key_of_the_reloadable_sections_has_a_decision() -> None:
    for section, model in SECTIONS.items():
        assert set(TABLE[section]) == set(model.model_fields), section


@pytest.mark.parametrize(("section", "key"), [(s, k) for s, keys in TABLE.items() for k in keys if k != "tls"])
def test_a_key_that_is_not_live_is_reported_as_needing_a_restart_and_a_live_one_is_not(
        section: str, key: str, certificates: Path) -> None:
    renew(certificates, "one")
    old = render(base_for(section, key), certificates)
    renew(certificates, "two")
    needed = restart_needed(old, changed(section, key, certificates))
    if TABLE[section][key].live:
        assert needed == []
    else:
        (entry,) = needed
        assert entry.startswith(f"[{section}] {key} (")


@pytest.mark.parametrize(("section", "key"), [(s, k) for s, keys in LIVE_KEYS.items() for k in sorted(keys)])
async def test_every_live_key_is_applied_by_a_reload(section: str, key: str, certificates: Path) -> None:
    change = TABLE.get(section, {}).get(key)
    assert change is not None and change.live, f"LIVE_KEYS has {section}.{key}, but this table does not say it is live"
    assert change.seen is not None
    renew(certificates, "one")
    gateway = Gateway(render(base_for(section, key), certificates))
    assert change.seen(gateway) != change.expected  # not so before the reload
    renew(certificates, "two")
    assert await gateway.apply(changed(section, key, certificates))
    assert gateway.config_status.restart_needed == ()
    assert change.seen(gateway) == change.expected


def test_a_section_within_a_section_adds_to_what_needs_a_restart(certificates: Path) -> None:
    """``[modbus.tls]`` added and ``[modbus] listen`` changed: both named (neither hides the other)."""
    ascii_link = '[[link]]\nname = "press"\nprotocol = "slc-ascii"\nport = "/dev/ttyUSB0"\nunit = 9\n'
    tls = (f'[modbus.tls]\nlisten = "0.0.0.0:8020"\ncert = "{certificates / "one.pem"}"\n'
           f'key = "{certificates / "one.key"}"\n')
    old = parse_config('[modbus]\nlisten = "0.0.0.0:5020"\n' + ascii_link)
    new = parse_config('[modbus]\nlisten = "0.0.0.0:5021"\n' + tls + ascii_link)
    assert restart_needed(old, new) == ['[modbus] listen ("0.0.0.0:5020" -> "0.0.0.0:5021")', "[modbus.tls] added"]
