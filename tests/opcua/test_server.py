"""The OPC UA server with asyncua's client (the unit tests; node-opcua's client is the end-to-end test,
tests/e2e/test_opcua_node_client.py): address space, reads and their quality, demand, writes, security,
reload.  The controllers are the DF1 SLC 5/04 simulator over TCP; expected values come from its
documented initial table (N7:n = n with the ladder frozen) and its memory, not from the gateway's code.
"""

from __future__ import annotations

import asyncio
import dataclasses
import shutil
import struct
from collections import Counter
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import UaStatusCodeError

from gateway.app import Gateway
from gateway.config import parse_config
from gateway.modbus.mapping import Table
from gateway.opcua.certs import ensure_certificate
from gateway.opcua.points import point_value
from gateway.unit import Source
from tests.net import free_port
from tests.opcua.plant import USERS, Line, eventually, link_text, opcua_text

DEMO = (Path(__file__).resolve().parents[2] / "config" / "demo.toml").read_text(encoding="utf-8")


pytestmark = pytest.mark.usefixtures("forget_simulators")


@pytest.fixture
async def lines() -> AsyncIterator[tuple[Line, Line]]:
    press, oven = await Line.start(seed=1), await Line.start(seed=2)
    try:
        yield press, oven
    finally:
        await press.off()
        await oven.off()


def config(tmp_path: Path, port: int, press: Line, oven: Line, *, press_keys: dict[str, Any] | None = None,
           **opcua: Any) -> Any:
    text = opcua_text(port, tmp_path, **opcua) + link_text("press", 1, press, **(press_keys or {}))
    text += link_text("oven", 2, oven, read_only=True)
    return parse_config(text)


def client(port: int, user: str | None = None) -> Client:
    found = Client(f"opc.tcp://127.0.0.1:{port}", timeout=10)
    if user is not None:
        found.set_user(user)
        found.set_password(dict((name, password) for name, password, _ in USERS)[user])
    return found


async def node(c: Client, text: str) -> Any:
    ns = await c.get_namespace_index("urn:slc-gateway")
    return c.get_node(ua.NodeId(text, ns))


async def good(variable: Any) -> ua.DataValue:
    found: list[ua.DataValue] = []

    async def check() -> bool:
        found[:] = [await variable.read_data_value(raise_on_bad_status=False)]
        return bool(found[0].StatusCode.is_good())

    await eventually(check)
    return found[0]


async def test_address_space_types_access_and_values_equal_modbus(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    async with Gateway(config(tmp_path, port, press, oven)) as gw, client(port) as c:
        ns = await c.get_namespace_index("urn:slc-gateway")
        names = {(await child.read_browse_name()).Name for child in await c.nodes.objects.get_children()}
        assert {"press", "oven"} <= names
        press_folder = c.get_node(ua.NodeId("press", ns))
        variables = {(await v.read_browse_name()).Name: v for v in await press_folder.get_children()}
        assert {"N7:0", "N7:7", "F8:0", "F8:1", "B3:0/0", "B3:0/3", "N7:50", "N7:51", "_Status"} <= set(variables)
        status = {(await v.read_browse_name()).Name for v in await variables["_Status"].get_children()}
        assert {"link_up", "data_age", "last_fault", "transactions", "errors", "retries"} <= status
        types = {"N7:0": ua.VariantType.Int16, "F8:0": ua.VariantType.Float, "B3:0/0": ua.VariantType.Boolean}
        for name, variant in types.items():
            assert await variables[name].read_data_type_as_variant_type() == variant
        assert (await node(c, "press.N7:50")).nodeid == ua.NodeId("press.N7:50", ns)
        read_only = await (await node(c, "press.N7:50")).read_attribute(ua.AttributeIds.AccessLevel)
        assert read_only.Value.Value == ua.AccessLevel.CurrentRead.mask
        writable = await (await node(c, "press.N7:1")).read_attribute(ua.AttributeIds.AccessLevel)
        assert writable.Value.Value & ua.AccessLevel.CurrentWrite.mask
        oven_point = await (await node(c, "oven.N7:1")).read_attribute(ua.AttributeIds.AccessLevel)
        assert oven_point.Value.Value == ua.AccessLevel.CurrentRead.mask  # a read_only link
        # the DF1 initial table: N7:n = n; the same moment over Modbus
        value = await good(await node(c, "press.N7:3"))
        assert value.Value.Value == 3
        assert value.SourceTimestamp is not None and value.ServerTimestamp is not None
        assert value.SourceTimestamp <= value.ServerTimestamp
        unit = gw.units[0]
        for address in range(8):
            dv = await good(await node(c, f"press.N7:{address}"))
            modbus = struct.unpack(">h", unit.read_register_bytes(Table.HOLDING, address, 1, Source.PEEK))[0]
            assert dv.Value.Value == modbus == press.sim.word("N7", address)
        link_up = await (await node(c, "press.status.link_up")).read_data_value()
        assert link_up.Value.Value == 1 and link_up.StatusCode.is_good()


async def test_quality_follows_the_link_down_and_back(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    async with Gateway(config(tmp_path, port, press, oven)), client(port) as c:
        variable = await node(c, "press.N7:2")
        await good(variable)
        changes: list[ua.DataValue] = []

        class Handler:
            def datachange_notification(self, _node: Any, _value: Any, data: Any) -> None:
                changes.append(data.monitored_item.Value)

        subscription = await c.create_subscription(100, Handler())
        await subscription.subscribe_data_change(variable)
        await eventually(lambda: _true(bool(changes) and changes[-1].StatusCode.is_good()))
        await press.off()
        started = asyncio.get_running_loop().time()

        async def bad() -> bool:
            dv = await variable.read_data_value(raise_on_bad_status=False)
            return bool(dv.StatusCode.value == ua.StatusCodes.BadNoCommunication)

        await eventually(bad, 10, 0.02)
        assert asyncio.get_running_loop().time() - started <= 1.0 + 1.0  # stale_after + 1 s
        await eventually(lambda: _true(changes[-1].StatusCode.value == ua.StatusCodes.BadNoCommunication), 3)
        await press.on()
        await good(variable)
        await eventually(lambda: _true(changes[-1].StatusCode.is_good() and changes[-1].Value.Value == 2))


async def _true(value: bool) -> bool:
    return value


async def test_stale_under_hold_is_the_last_usable_value(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    keys = {"offline": "hold", "down_after_failures": 1000, "down_after_seconds": 600, "stale_after": 0.5}
    async with Gateway(config(tmp_path, port, press, oven, press_keys=keys)), client(port) as c:
        variable = await node(c, "press.N7:1")
        await good(variable)
        quiet = press.sim.options
        press.sim.options = dataclasses.replace(quiet, lose_in=1)  # the controller answers nothing; the link stays up

        async def held() -> bool:
            dv = await variable.read_data_value(raise_on_bad_status=False)
            return bool(dv.StatusCode.value == ua.StatusCodes.UncertainLastUsableValue and dv.Value.Value == 1)

        await eventually(held, 10)
        press.sim.options = quiet
        await good(variable)


async def test_demand_of_reads_and_monitored_items(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    async with Gateway(config(tmp_path, port, press, oven)) as gw, client(port) as c:
        unit = gw.units[0]
        assert gw.opcua is not None
        noted: list[tuple[Table, int, int]] = []
        note = unit.note_demand

        def spy(table: Table, address: int, count: int) -> None:
            noted.append((table, address, count))
            note(table, address, count)

        unit.note_demand = spy  # type: ignore[method-assign]
        await good(await node(c, "press.N7:4"))
        assert (Table.HOLDING, 4, 1) in noted  # a Read is demand, as a Modbus read
        subscription = await c.create_subscription(100, None)
        variable = await node(c, "press.F8:1")
        params = ua.MonitoredItemCreateRequest()
        params.ItemToMonitor = ua.ReadValueId(NodeId=variable.nodeid, AttributeId=ua.AttributeIds.Value)
        params.MonitoringMode = ua.MonitoringMode.Reporting
        params.RequestedParameters = ua.MonitoringParameters(ClientHandle=1, SamplingInterval=1.0, QueueSize=1)
        result = (await c.uaclient.create_monitored_items(ua.CreateMonitoredItemsParameters(
            SubscriptionId=subscription.subscription_id, ItemsToCreate=[params],
            TimestampsToReturn=ua.TimestampsToReturn.Both)))[0]
        assert result.StatusCode.is_good()
        # revised to what the line does for its block: never faster than its class period or its achieved refresh
        block = unit.plan.registers(Table.HOLDING)[102].block
        schedule = unit.schedule
        assert schedule is not None
        floor = 1000 * max(schedule.period[block], schedule.refresh_period([block]) or 0.0)
        assert result.RevisedSamplingInterval >= max(1.0, floor * 0.5)
        face = gw.opcua.links["press"]
        await eventually(lambda: _true(len(face.book) == 1))

        def of_its_block() -> int:  # its block's demand is noted (once a block, not once a point)
            return sum(1 for table, address, count in noted
                       if unit.images.blocks_in(table, address, count) == (block,))

        noted.clear()
        await eventually(lambda: _true(of_its_block() >= 2), 5)  # demanded again and again
        await subscription.delete()
        await eventually(lambda: _true(len(face.book) == 0))  # nobody holds it: no more demand
        noted.clear()
        await asyncio.sleep(1.2)
        assert of_its_block() == 0


async def test_writes_take_the_write_path(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    async with Gateway(config(tmp_path, port, press, oven)) as gw:
        async with client(port, "operator") as c:
            await good(await node(c, "press.N7:5"))
            await (await node(c, "press.N7:5")).write_value(ua.DataValue(ua.Variant(1234, ua.VariantType.Int16)))
            assert press.sim.word("N7", 5) == 1234  # Good only once the controller confirmed it
            await (await node(c, "press.F8:1")).write_value(ua.DataValue(ua.Variant(2.5, ua.VariantType.Float)))
            assert press.sim.float_value("F8", 1) == 2.5
            await (await node(c, "press.B3:0/1")).write_value(ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
            assert press.sim.word("B3", 0) & 0b10
            refused = {
                "press.N7:50": (ua.Variant(9, ua.VariantType.Int16), ua.StatusCodes.BadNotWritable),  # input
                "press.status.errors": (ua.Variant(9, ua.VariantType.UInt16), ua.StatusCodes.BadNotWritable),
                "oven.N7:1": (ua.Variant(9, ua.VariantType.Int16), ua.StatusCodes.BadNotWritable),  # read_only link
                "press.N7:6": (ua.Variant(40000, ua.VariantType.Int32), ua.StatusCodes.BadOutOfRange),
                "press.N7:7": (ua.Variant(1.5, ua.VariantType.Float), ua.StatusCodes.BadTypeMismatch),
            }
            for text, (variant, code) in refused.items():
                with pytest.raises(UaStatusCodeError) as caught:
                    await (await node(c, text)).write_value(ua.DataValue(variant))
                assert caught.value.code == code, text
        async with client(port, "viewer") as c:  # a read-only user
            with pytest.raises(UaStatusCodeError) as caught:
                await (await node(c, "press.N7:2")).write_value(ua.DataValue(ua.Variant(5, ua.VariantType.Int16)))
            assert caught.value.code == ua.StatusCodes.BadNotWritable
        async with client(port) as c:  # anonymous: read only
            with pytest.raises(UaStatusCodeError) as caught:
                await (await node(c, "press.N7:2")).write_value(ua.DataValue(ua.Variant(5, ua.VariantType.Int16)))
            assert caught.value.code == ua.StatusCodes.BadNotWritable
        await press.off()
        await eventually(lambda: _true(not gw.units[0].verdict(asyncio.get_running_loop().time()).up), 10)
        async with client(port, "operator") as c:
            with pytest.raises(UaStatusCodeError) as caught:
                await (await node(c, "press.N7:3")).write_value(ua.DataValue(ua.Variant(7, ua.VariantType.Int16)))
            assert caught.value.code == ua.StatusCodes.BadCommunicationError
        assert gw.opcua is not None and gw.opcua.write_failures == 1
    applied = Counter(entry[1] for entry in press.sim.applied_writes)
    assert applied == {"N7:5": 1, "F8:1": 1, "B3:0": 1}
    assert press.sim.word("N7", 2) == 2 and press.sim.word("N7", 6) == 6 and oven.sim.word("N7", 1) == 1


async def test_write_applied_exactly_once_under_line_faults(tmp_path: Path) -> None:
    press = await Line.start(seed=7, corrupt=10, drop=15, withhold_ack=10, duplicate=10, noise=10)
    oven = await Line.start(seed=8)
    port = free_port()
    try:
        async with Gateway(config(tmp_path, port, press, oven)), client(port, "operator") as c:
            await good(await node(c, "press.N7:5"))
            for address, value in ((5, 1111), (6, -2), (7, 3333)):
                variable = await node(c, f"press.N7:{address}")
                try:
                    await variable.write_value(ua.DataValue(ua.Variant(value, ua.VariantType.Int16)))
                except UaStatusCodeError as exc:  # never Good for a write the controller did not confirm
                    assert exc.code == ua.StatusCodes.BadTimeout
                else:
                    assert press.sim.word("N7", address) == value & 0xFFFF
    finally:
        await press.off()
        await oven.off()
    applied = Counter(entry[1] for entry in press.sim.applied_writes)
    assert applied == {"N7:5": 1, "N7:6": 1, "N7:7": 1}


async def test_a_write_without_a_verdict_is_bad_timeout_never_good(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    keys = {"down_after_failures": 1000, "down_after_seconds": 600, "write_timeout": 0.5}
    async with Gateway(config(tmp_path, port, press, oven, press_keys=keys)), client(port, "operator") as c:
        variable = await node(c, "press.N7:5")
        await good(variable)
        quiet = press.sim.options
        press.sim.options = dataclasses.replace(quiet, lose_in=1)  # the controller hears nothing; the link stays up
        started = asyncio.get_running_loop().time()
        with pytest.raises(UaStatusCodeError) as caught:
            await variable.write_value(ua.DataValue(ua.Variant(555, ua.VariantType.Int16)))
        assert caught.value.code == ua.StatusCodes.BadTimeout
        assert asyncio.get_running_loop().time() - started >= 0.5
        press.sim.options = quiet
    assert press.sim.applied_writes == [] and press.sim.word("N7", 5) == 5


async def test_security_certificates_users_and_anonymous(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    trusted_cert, trusted_key = tmp_path / "client" / "cert.der", tmp_path / "client" / "key.pem"
    ensure_certificate(trusted_cert, trusted_key, "urn:test:trusted-client")
    stranger_cert, stranger_key = tmp_path / "stranger" / "cert.der", tmp_path / "stranger" / "key.pem"
    ensure_certificate(stranger_cert, stranger_key, "urn:test:stranger")
    (tmp_path / "trusted").mkdir()
    shutil.copy(trusted_cert, tmp_path / "trusted" / "client.der")
    secure = "Basic256Sha256,SignAndEncrypt,{},{}"
    async with Gateway(config(tmp_path, port, press, oven, anonymous="none")) as gw:
        assert (tmp_path / "server" / "cert.der").is_file()  # generated
        c = client(port, "operator")
        c.application_uri = "urn:test:trusted-client"
        await c.set_security_string(secure.format(trusted_cert, trusted_key))
        async with c:
            endpoints = {(e.SecurityPolicyUri.split("#")[-1], e.SecurityMode.name) for e in await c.get_endpoints()}
            assert endpoints == {("None", "None_"), ("Basic256Sha256", "SignAndEncrypt")}
            variable = await node(c, "press.N7:4")
            await good(variable)
            await variable.write_value(ua.DataValue(ua.Variant(44, ua.VariantType.Int16)))
        assert press.sim.word("N7", 4) == 44
        stranger = client(port, "operator")
        stranger.application_uri = "urn:test:stranger"
        await stranger.set_security_string(secure.format(stranger_cert, stranger_key))
        with pytest.raises(UaStatusCodeError) as caught:
            async with stranger:
                pass
        assert caught.value.code == ua.StatusCodes.BadSecurityChecksFailed
        rejected = list((tmp_path / "rejected").iterdir())
        assert [path.read_bytes() for path in rejected] == [stranger_cert.read_bytes()]
        with pytest.raises(UaStatusCodeError) as caught:  # anonymous = "none": no endpoint offers the token
            async with client(port):
                pass
        assert caught.value.code == ua.StatusCodes.BadIdentityTokenRejected
        wrong = client(port, "operator")
        wrong.set_password("not-the-password")
        with pytest.raises(UaStatusCodeError) as caught:
            async with wrong:
                pass
        assert caught.value.code == ua.StatusCodes.BadUserAccessDenied
        # the stranger's certificate, the anonymous session, the password: each a rejected login
        assert gw.opcua is not None and gw.opcua.rejected_logins == 3


async def test_reload_adds_and_removes_link_folders_keeping_sessions(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    press, oven = lines
    port = free_port()
    both = config(tmp_path, port, press, oven)
    press_only = parse_config(opcua_text(port, tmp_path) + link_text("press", 1, press))
    async with Gateway(press_only) as gw, client(port) as c:
        ns = await c.get_namespace_index("urn:slc-gateway")
        variable = await node(c, "press.N7:2")
        await good(variable)

        async def folders() -> set[str]:
            return {(await child.read_browse_name()).Name for child in await c.nodes.objects.get_children()
                    if child.nodeid.NamespaceIndex == ns}

        assert await folders() == {"press"}
        assert await gw.apply(both)
        assert await folders() == {"press", "oven"}
        await good(await node(c, "oven.N7:3"))
        assert await gw.apply(press_only)
        assert await folders() == {"press"}
        assert (await variable.read_data_value()).Value.Value == 2  # the same session, the same NodeId


async def test_every_tag_of_the_demo_equals_modbus_at_the_same_moment(tmp_path: Path) -> None:
    """Every variable of config/demo.toml, as the Read service answers it, against the Modbus read of its
    registers in the same event-loop step (the ladders run: only the same moment compares), then the same
    over the wire: every variable Good once its block was read."""
    port = free_port()
    demo = DEMO.replace('listen = "127.0.0.1:5020"', 'listen = "127.0.0.1:0"').replace(
        'listen = "127.0.0.1:9108"', 'listen = "127.0.0.1:0"')
    text = demo.replace("[[link]]", f'[opcua]\nlisten = "opc.tcp://127.0.0.1:{port}"\nsecurity = ["None"]\n\n'
                        "[[link]]", 1)
    async with Gateway(parse_config(text, base_dir=tmp_path)) as gw:
        assert gw.opcua is not None
        server = gw.opcua

        def all_read() -> bool:
            return all(unit.cache.stamps[b] != float("-inf") for unit in gw.units for b in range(len(unit.plan.blocks)))

        await eventually(lambda: _true(all_read()), 60, 0.2)
        compared = 0
        for face in server.links.values():
            unit = face.unit
            for index, point in enumerate(face.points):
                if point.block is None:
                    continue
                data_value = server._read_value(face.node_ids[index], ua.AttributeIds.Value)  # the Read service's
                count = 1 if point.bits else point.width
                if point.bits:
                    modbus_bits = unit.read_bit_bytes(point.table, point.address, count, Source.PEEK)
                    modbus: object = bool(modbus_bits[0] & 1)
                else:
                    modbus = point_value(point, unit.read_register_bytes(point.table, point.address, count,
                                                                         Source.PEEK))
                assert data_value.StatusCode.is_good(), (point.node_id, data_value.StatusCode)
                assert data_value.Value.Value == modbus, point.node_id
                compared += 1
        assert compared >= 200
        async with client(port) as c:  # over the wire: one Read of every variable, every one Good
            ids = [node_id for face in server.links.values() for node_id in face.node_ids]
            read = ua.ReadParameters(NodesToRead=[ua.ReadValueId(NodeId=i, AttributeId=ua.AttributeIds.Value)
                                                  for i in ids])
            values = await c.uaclient.read(read)
            assert len(values) == len(ids)
            bad = [(i.Identifier, v.StatusCode.name) for i, v in zip(ids, values, strict=True)
                   if not v.StatusCode.is_good()]
            assert bad == []


async def test_the_sign_only_endpoint_takes_a_session(tmp_path: Path, lines: tuple[Line, Line]) -> None:
    """``Basic256Sha256-Sign``: signed, not encrypted; the trusted client's session reads and writes (the
    password is encrypted with the policy, the channel only signed)."""
    press, oven = lines
    port = free_port()
    cert, key = tmp_path / "client" / "cert.der", tmp_path / "client" / "key.pem"
    ensure_certificate(cert, key, "urn:test:signing-client")
    (tmp_path / "trusted").mkdir()
    shutil.copy(cert, tmp_path / "trusted" / "client.der")
    async with Gateway(config(tmp_path, port, press, oven, security=["Basic256Sha256-Sign"])) as gw:
        c = client(port, "operator")
        c.application_uri = "urn:test:signing-client"
        await c.set_security_string(f"Basic256Sha256,Sign,{cert},{key}")
        async with c:
            endpoints = {(e.SecurityPolicyUri.split("#")[-1], e.SecurityMode.name) for e in await c.get_endpoints()}
            assert endpoints == {("Basic256Sha256", "Sign")}
            variable = await node(c, "press.N7:6")
            assert (await good(variable)).Value.Value == 6
            await variable.write_value(ua.DataValue(ua.Variant(66, ua.VariantType.Int16)))
        assert press.sim.word("N7", 6) == 66
        plain = client(port, "operator")  # no None endpoint is offered
        with pytest.raises(ua.UaError, match="No matching endpoints"):
            async with plain:
                pass
        assert gw.opcua is not None and gw.opcua.rejected_logins == 0


async def test_opcua_and_modbus_writes_of_one_register_are_applied_in_arrival_order(
        tmp_path: Path) -> None:
    """The one write path: an OPC UA write queued before a Modbus write of the same register is applied
    before it, though the Modbus connection, never served yet, would be served first between clients."""
    from pymodbus.client import AsyncModbusTcpClient

    press = await Line.start(seed=1, delay=0.3)  # every transaction holds the line 0.3 s: the writes queue
    oven = await Line.start(seed=2)
    port = free_port()
    try:
        async with Gateway(config(tmp_path, port, press, oven)) as gw, client(port, "operator") as first, \
                client(port, "operator") as second:
            assert gw.opcua is not None
            server = gw.opcua
            await good(await node(first, "press.N7:5"))
            modbus = AsyncModbusTcpClient("127.0.0.1", port=gw.port, timeout=10, retries=0)
            assert await modbus.connect()
            try:
                written: list[asyncio.Task[Any]] = []

                async def received(count: int) -> None:  # the server took it: it is in the write queue
                    await eventually(lambda: _true(server.writes == count), 5, 0.005)

                for c, value in ((first, 1111), (second, 3333)):  # two sessions: asyncua answers one at a time
                    variable = await node(c, "press.N7:5")
                    written.append(asyncio.create_task(
                        variable.write_value(ua.DataValue(ua.Variant(value, ua.VariantType.Int16)))))
                    await received(len(written))
                reply = await modbus.write_registers(5, [2222], device_id=1)
                assert not reply.isError()
                await asyncio.gather(*written)
            finally:
                modbus.close()
        order = [struct.unpack("<h", data[-2:])[0] for _, element, data in press.sim.applied_writes
                 if element == "N7:5"]
        assert order == [1111, 3333, 2222]
        assert press.sim.word("N7", 5) == 2222
    finally:
        await press.off()
        await oven.off()
