"""The OPC UA server on asyncua (LGPL-3.0, used as a library, unmodified): the one module that imports it.

A thin loop around the sans-I/O parts (``gateway.opcua.quality``, ``gateway.opcua.points``,
``gateway.opcua.publish``):

* **Address space**: ``Objects/<link>/<tag>`` and ``Objects/<link>/_Status/<key>``, NodeIds
  ``ns=<urn:slc-gateway>;s=<link>.<tag>`` (``gateway.opcua.points``).  Read-only points have
  AccessLevel CurrentRead only.
* **Read service**: each variable's value is computed when read (asyncua's value callback): its
  block is noted as demand, as a Modbus read's is, and its status code comes from the one verdict.
  A variable nobody monitors costs nothing between Reads: asyncua holds no value of it.
* **Subscriptions**: every pass (``pass_period``) the server looks at the blocks stored since the
  last one (the unit's cache tells it, as it tells the Sparkplug node) and, every ``_CHECK_INTERVAL``,
  at what ages without a store (links down, blocks going stale) (``LinkWatch``); a monitored
  variable whose value or status code changed is handed, as one DataValue, to its monitored items
  (asyncua's data change callbacks of the node), which queue it for their subscriptions.  It reads
  by peeking (no demand); the monitored items' demand is noted per block at their sampling interval
  (``DemandBook``), which is revised up to what the line achieves for the block.  A pass lets other
  work in (Modbus answers) each time it has held the event loop ``_SLICE``.
* **Writes** take the unit's write path (``Unit.write_registers`` / ``write_bits``: the queue shared
  with Modbus and Sparkplug, ``write_timeout``, at most once); Good only once the controller confirmed.
* **Security**: the endpoints of ``security``; on Sign and SignAndEncrypt the client's certificate
  must be in ``trusted_clients`` (else Bad_SecurityChecksFailed at ActivateSession, logged once
  with its thumbprint, written to ``rejected``); users by name and password hash; anonymous read or none.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Sequence
from datetime import UTC
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.callback import CallbackType, ServerItemCallback
from asyncua.common.node import Node
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.address_space import AddressSpace, AttributeService, AttributeValue
from asyncua.server.user_managers import UserManager

from gateway.clients import Client, audit_write, current_client
from gateway.config.link import LinkBase
from gateway.config.opcua import OpcUaConfig
from gateway.errors import ModbusExceptionReply
from gateway.opcua.certs import application_uri, ensure_certificate, thumbprint, trusted_thumbprints
from gateway.opcua.passwords import verify_password
from gateway.opcua.points import OPCUA_NAMESPACE, OpcPoint, link_points, point_registers, read_point, status_point_value
from gateway.opcua.publish import LinkWatch
from gateway.opcua.quality import Code, Reading, pass_period, revise_interval, write_status
from gateway.unit import Unit

__all__ = ["OpcUaServer"]

log = logging.getLogger("gateway.opcua")

#: seconds between the passes that look at what ages without a store (stale blocks, links down, status values)
_CHECK_INTERVAL: Final = 0.5
#: the longest the publishing pass holds the event loop before it lets other work (Modbus answers) in (s)
_SLICE: Final = 0.0005
#: the longest session timeout granted (s): a client gone without closing its session holds its demand this long
_SESSION_TIMEOUT: Final = 60.0
_POLICIES: Final = {
    "None": ua.SecurityPolicyType.NoSecurity,
    "Basic256Sha256-Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "Basic256Sha256-SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
}
_VARIANTS: Final = {"Boolean": ua.VariantType.Boolean, "Int16": ua.VariantType.Int16,
                    "UInt16": ua.VariantType.UInt16, "Int32": ua.VariantType.Int32,
                    "UInt32": ua.VariantType.UInt32, "Float": ua.VariantType.Float}
_GOOD_STATUS: Final = Reading(Code.GOOD, True)
#: what the value setter returns (asyncua ignores it)
_NOTHING: Final = ua.DataValue()
#: asyncua's default user of a write (its own, internal session)
_ADMIN: Final = User(role=UserRole.Admin)


def _keep(*_: object) -> ua.DataValue:
    """The value setter of the links' variables: what the server writes goes to the subscriptions only."""
    return _NOTHING


def _node_id(text: str, namespace: int) -> ua.NodeId:
    return ua.NodeId(ua.String(text), ua.Int16(namespace))


def _status_code(code: Code) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(getattr(ua.StatusCodes, code.value)))


#: each code's StatusCode, made once (asyncua never changes a StatusCode it is given)
_STATUS_CODES: Final = {code: _status_code(code) for code in Code}


class _Link(LinkWatch):
    """One link's folder: its variables as asyncua knows them, and what the passes published of them."""

    def __init__(self, link: LinkBase, unit: Unit[Any, Any], namespace: int) -> None:
        super().__init__(unit, link_points(link, unit))
        self.name = link.name
        self.node_ids = [_node_id(point.node_id, namespace) for point in self.points]
        #: per point: its variant type
        self.variants = [_VARIANTS[point.data_type] for point in self.points]
        #: per point: asyncua's record of its Value attribute (set when the node is added): a monitored item
        #: of it is a data change callback there
        self.values: list[AttributeValue] = []
        #: the server's count of monitored items gone when this link last looked for its own
        self.looked = -1
        self.folder: Node | None = None
        self.listener = self.stored

    def look(self, now: float) -> None:
        """Find the points that have a monitored item now."""
        self.watch((index for index, value in enumerate(self.values) if value.datachange_callbacks), now)


class _Published(ua.DataValue):
    """A value the server made: never changed after it is made, so asyncua's copy of it for each
    monitored item (``copy.deepcopy`` of every field, datetimes included: most of its cost of a data
    change) can be the value itself.  Encoded as the DataValue it is."""

    def __deepcopy__(self, _memo: object) -> _Published:
        return self


class _Users(UserManager):
    """Who may open a session: users by password hash, anonymous as configured; on a signed channel, only
    clients whose certificate is trusted."""

    def __init__(self, server: OpcUaServer) -> None:
        self._server = server
        self._users = {user.name: user for user in server.config.user}

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        server = self._server
        if certificate:  # the secure channel's client certificate (b"" on a None channel)
            server.check_client(bytes(certificate))
        if username is None:
            if server.config.anonymous == "none":
                server.refuse_login("an anonymous session (anonymous = \"none\")")
                raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)
            return User(role=UserRole.User, name=None)
        user = self._users.get(username)
        if user is None or not verify_password(password or "", user.password_hash):
            server.refuse_login(f"user {username!r}: wrong user name or password")
            return None
        return User(role=UserRole.User, name=username)


class _Attributes(AttributeService):
    """asyncua's attribute service, whose writes of the links' variables take the gateway's write path."""

    def __init__(self, aspace: AddressSpace, server: OpcUaServer) -> None:
        super().__init__(aspace)
        self._server = server

    async def write(self, params: ua.WriteParameters, user: User = _ADMIN) -> list[ua.StatusCode]:
        results: list[ua.StatusCode] = []
        for item in params.NodesToWrite:
            found = self._server.point_at(item.NodeId) if item.AttributeId == ua.AttributeIds.Value else None
            if found is None:
                results.extend(await super().write(ua.WriteParameters(NodesToWrite=[item]), user))
            else:
                results.append(await self._server.write(found[0], found[1], item.Value, user))
        return results


class OpcUaServer:
    """The gateway's OPC UA server (``[opcua]``): :meth:`start`, then :meth:`run` until cancelled, :meth:`close`."""

    def __init__(self, config: OpcUaConfig, links: Sequence[LinkBase], units: Sequence[Unit[Any, Any]]) -> None:
        self.config = config
        self._pairs = list(zip(links, units, strict=True))
        self.links: dict[str, _Link] = {}
        self._by_node: dict[str, tuple[_Link, int]] = {}
        self._server: Server | None = None
        self._namespace = 0
        self._offset = 0.0  # wall seconds - loop seconds
        #: counters for /api/status and /metrics
        self.rejected_logins = 0
        self.data_changes = 0
        self.writes = 0
        self.write_failures = 0
        #: CPU seconds of the publishing passes (reading the images, handing changes to asyncua)
        self.cpu_seconds = 0.0
        #: (loop time, data_changes) at the last check passes: the publish rate over the last 10 s
        self._rate: deque[tuple[float, int]] = deque(maxlen=int(10 / _CHECK_INTERVAL) + 1)
        self._trusted: set[str] = set()
        self._rejected_logged: set[str] = set()
        self._clients: dict[str | None, Client] = {}
        #: the subscriptions at the last check pass, and a count of monitored items gone (items deleted,
        #: subscriptions gone): a link looks for its monitored items again when it changes
        self._subscriptions: set[int] = set()
        self._items_gone = 0

    # --- lifecycle -----------------------------------------------------------------------------

    async def start(self) -> None:
        """Build the address space and listen (OSError: the port is taken)."""
        config = self.config
        loop = asyncio.get_running_loop()
        self._offset = time.time() - loop.time()
        uri = application_uri()
        server = Server(user_manager=_Users(self))
        # a session whose connection is gone (asyncua keeps it, with its subscriptions, for the client to come
        # back) is closed after at most this long: its monitored items stop demanding then
        server.iserver.max_session_timeout_ms = _SESSION_TIMEOUT * 1000
        server.iserver.attribute_service = _Attributes(server.iserver.aspace, self)
        await server.init()
        await server.set_application_uri(uri)
        server.set_server_name("slc-gateway")
        server.set_endpoint(config.listen)
        server.set_security_policy([_POLICIES[name] for name in config.security])
        tokens: list[type] = [ua.UserNameIdentityToken]
        if config.anonymous == "read":
            tokens.insert(0, ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        if any(name != "None" for name in config.security):
            await asyncio.to_thread(ensure_certificate, config.certificate, config.private_key, uri)
            await server.load_certificate(str(config.certificate))
            await server.load_private_key(str(config.private_key))
            self._trusted = trusted_thumbprints(config.trusted_clients)
        self._namespace = await server.register_namespace(OPCUA_NAMESPACE)
        server.subscribe_server_callback(CallbackType.ItemSubscriptionCreated, self._items_created)
        server.subscribe_server_callback(CallbackType.ItemSubscriptionDeleted, self._items_deleted)
        self._server = server
        for link, unit in self._pairs:
            await self._add_link(link, unit)
        await server.start()
        # the endpoints were made at start from the tokens offered (no anonymous one under anonymous = "none");
        # from now on asyncua lets an anonymous token through to _Users, which refuses it and counts it
        server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
        log.info("opcua: serving %d links on %s (%s)", len(self.links), config.listen, ", ".join(config.security))

    async def run(self) -> None:
        """Publish what changed to the monitored items, until cancelled."""
        loop = asyncio.get_running_loop()
        next_check = loop.time()
        while True:
            await asyncio.sleep(self._pass_period())
            now = loop.time()
            check = now >= next_check
            if check:
                next_check = now + _CHECK_INTERVAL
                self._rate.append((now, self.data_changes))
                self._count_gone()
            yielded = time.perf_counter()
            for link in list(self.links.values()):
                started = time.thread_time()
                await self._pass(link, now, check)
                self.cpu_seconds += time.thread_time() - started
                if time.perf_counter() - yielded > _SLICE:
                    await asyncio.sleep(0)  # Modbus answers go in between
                    yielded = time.perf_counter()

    def _pass_period(self) -> float:
        """Seconds to the next publishing pass: ``publish_interval``, or half the shortest publishing interval
        of the subscriptions when that is longer (a 1 s subscription is sent what the last 0.5 s brought: the
        reads of a block in that time are judged once; every pass is then a check pass)."""
        server = self._server
        subscriptions = server.iserver.subscription_service.subscriptions if server is not None else {}
        shortest = min((sub.data.RevisedPublishingInterval for sub in subscriptions.values()), default=0.0)
        return pass_period(self.config.publish_interval, shortest, _CHECK_INTERVAL)

    async def close(self) -> None:
        """Close every session and stop listening (SIGTERM)."""
        for link in self.links.values():
            self._detach(link)
        if self._server is not None:
            server, self._server = self._server, None
            await server.stop()
            log.info("opcua: server stopped")

    async def relink(self, links: Sequence[LinkBase], units: Sequence[Unit[Any, Any]]) -> None:
        """After a config reload: the folders of links gone or replaced go, new ones come; sessions stay."""
        self._pairs = list(zip(links, units, strict=True))
        wanted = {link.name: (link, unit) for link, unit in self._pairs}
        for name, face in list(self.links.items()):
            if name not in wanted or wanted[name][1] is not face.unit:
                await self._remove_link(face)
        for name, (link, unit) in wanted.items():
            if name not in self.links:
                await self._add_link(link, unit)

    # --- the address space -----------------------------------------------------------------------

    async def _add_link(self, link: LinkBase, unit: Unit[Any, Any]) -> None:
        server = self._server
        if server is None:
            return
        face = _Link(link, unit, self._namespace)
        ns = self._namespace
        folder = await server.nodes.objects.add_folder(_node_id(link.name, ns), ua.QualifiedName(link.name, ns))
        status = await folder.add_folder(_node_id(f"{link.name}._Status", ns), ua.QualifiedName("_Status", ns))
        aspace = server.iserver.aspace
        for index, point in enumerate(face.points):
            parent = status if point.block is None else folder
            node_id = face.node_ids[index]
            variant = _VARIANTS[point.data_type]
            initial = ua.Variant(False if variant is ua.VariantType.Boolean else 0, variant)
            node = await parent.add_variable(node_id, ua.QualifiedName(point.browse_name, ns), initial,
                                             varianttype=variant)
            if point.description:
                await node.write_attribute(ua.AttributeIds.Description,
                                           ua.DataValue(ua.Variant(ua.LocalizedText(point.description))))
            if point.writable:
                await node.set_writable()
            aspace.set_attribute_value_callback(node_id, ua.AttributeIds.Value, self._read_value)
            aspace.set_attribute_value_setter(node_id, ua.AttributeIds.Value, _keep)  # its value is computed
            face.values.append(aspace[node_id].attributes[ua.AttributeIds.Value])
            self._by_node[point.node_id] = (face, index)
        face.folder = folder
        unit.cache.listeners.append(face.listener)
        face.look(asyncio.get_running_loop().time())
        self.links[link.name] = face

    async def _remove_link(self, face: _Link) -> None:
        self._detach(face)
        del self.links[face.name]
        for point in face.points:
            self._by_node.pop(point.node_id, None)
        if self._server is not None and face.folder is not None:
            await self._server.delete_nodes([face.folder], recursive=True)

    @staticmethod
    def _detach(face: _Link) -> None:
        with contextlib.suppress(ValueError):
            face.unit.cache.listeners.remove(face.listener)

    def point_at(self, node_id: ua.NodeId) -> tuple[_Link, int] | None:
        """The link and point of one of the links' NodeIds (None: another node)."""
        if node_id.NamespaceIndex != self._namespace or not isinstance(node_id.Identifier, str):
            return None
        return self._by_node.get(node_id.Identifier)

    # --- values ---------------------------------------------------------------------------------

    def _stamp(self, loop_time: float) -> ua.DateTime:
        return ua.DateTime.fromtimestamp(loop_time + self._offset, UTC)

    def _value_now(self, face: _Link, index: int, now: float) -> tuple[Reading, object, float]:
        point = face.points[index]
        if point.block is None:
            return _GOOD_STATUS, status_point_value(face.unit, point, now), now
        return read_point(face.unit, point, now)

    def _data_value(self, point: OpcPoint, reading: Reading, value: object, read_at: float,
                    now: float) -> ua.DataValue:
        variant = ua.Variant(value, _VARIANTS[point.data_type]) if value is not None else ua.Variant()
        return _Published(Value=variant, StatusCode=_STATUS_CODES[reading.code], SourceTimestamp=self._stamp(read_at),
                          ServerTimestamp=self._stamp(now))

    def _read_value(self, node_id: ua.NodeId, _attribute: ua.AttributeIds) -> ua.DataValue:
        """A Read of a variable (and a new monitored item's first value): demand, as a Modbus read."""
        found = self.point_at(node_id)
        if found is None:
            return ua.DataValue(StatusCode=ua.StatusCode(ua.UInt32(ua.StatusCodes.BadNodeIdUnknown)))
        face, index = found
        point = face.points[index]
        now = asyncio.get_running_loop().time()
        if point.block is not None:
            face.unit.note_demand(point.table, point.address, 1 if point.bits else point.width)
        reading, value, read_at = self._value_now(face, index, now)
        return self._data_value(point, reading, value, read_at, now)

    async def _items_created(self, event: ServerItemCallback, _dispatcher: Any) -> None:
        """Monitored items created: their sampling interval revised to what the line achieves, and demand."""
        now = asyncio.get_running_loop().time()
        for item, result in zip(event.request_params.ItemsToCreate, event.response_params, strict=False):
            found = self.point_at(item.ItemToMonitor.NodeId)
            if found is None or not result.StatusCode.is_good():
                continue
            face, index = found
            block = face.points[index].block
            schedule = face.unit.schedule
            period = achieved = None
            if block is not None and schedule is not None:
                period, achieved = schedule.period[block], schedule.refresh_period([block])
            publishing = result.RevisedSamplingInterval  # asyncua gives the subscription's publishing interval
            interval = revise_interval(item.RequestedParameters.SamplingInterval, publishing, period, achieved,
                                       pass_period(self.config.publish_interval, publishing, _CHECK_INTERVAL))
            result.RevisedSamplingInterval = interval
            face.created(index, interval / 1000.0, now)

    def _count_gone(self) -> None:
        """Count the subscriptions gone since the last check pass (a session closed, a subscription deleted or
        expired): the links look for their monitored items again (a deleted item is counted when deleted)."""
        server = self._server
        subscriptions = set(server.iserver.subscription_service.subscriptions) if server is not None else set()
        if subscriptions != self._subscriptions:
            self._subscriptions = subscriptions
            self._items_gone += 1

    async def _items_deleted(self, _event: ServerItemCallback, _dispatcher: Any) -> None:
        self._items_gone += 1

    async def _pass(self, face: _Link, now: float, check: bool) -> None:
        """Hand the changed values of ``face``'s monitored points to their monitored items (``LinkWatch``)."""
        if check:
            if face.looked != self._items_gone:
                face.looked = self._items_gone
                face.look(now)
            face.note_demand(now)
        changes = face.changes(now, check)
        if not changes:
            return
        self.data_changes += len(changes)
        server_at = self._stamp(now)
        stamped, source_at = now, server_at
        for index, code, value, read_at in changes:
            if read_at != stamped:
                stamped, source_at = read_at, self._stamp(read_at)
            variant = ua.Variant(value, face.variants[index]) if value is not None else ua.Variant()
            data_value = _Published(Value=variant, StatusCode=_STATUS_CODES[code], SourceTimestamp=source_at,
                                    ServerTimestamp=server_at)
            # what asyncua's AddressSpace.write_attribute_value does after its checks (the node is known, of
            # the right type, its value computed by _read_value): each monitored item of the node is told
            for handle, callback in list(face.values[index].datachange_callbacks.items()):
                try:
                    await callback(handle, data_value)
                except Exception:
                    log.exception("opcua: a monitored item of %s failed", face.points[index].node_id)

    # --- writes ---------------------------------------------------------------------------------

    def _can_write(self, user: User) -> bool:
        return user.name is not None and user.name in self.config.writers

    def _client(self, user: User) -> Client:
        """One write-queue client per user name (the audit log names it)."""
        client = self._clients.get(user.name)
        if client is None:
            client = self._clients[user.name] = Client(f"opcua user {user.name or '(anonymous)'}")
        return client

    async def write(self, face: _Link, index: int, data: ua.DataValue, user: User) -> ua.StatusCode:
        """A Write of a variable's value through the unit's write path; Good only once confirmed."""
        point = face.points[index]
        if not point.writable or point.block is None or not self._can_write(user):
            return _STATUS_CODES[Code.NOT_WRITABLE]
        value = data.Value.Value if data.Value is not None else None
        registers: list[int] = []
        try:
            if point.bits:
                if not isinstance(value, bool):
                    raise TypeError(f"{value!r} is not a Boolean")
            else:
                registers = point_registers(point, value)
        except TypeError:
            return _STATUS_CODES[Code.TYPE_MISMATCH]
        except ValueError:
            return _STATUS_CODES[Code.OUT_OF_RANGE]
        unit = face.unit
        loop = asyncio.get_running_loop()
        self.writes += 1
        token = current_client.set(self._client(user))
        started = loop.time()
        failure: ModbusExceptionReply | None = None
        try:
            if point.bits:
                await unit.write_bits(point.address, [bool(value)])
            else:
                await unit.write_registers(point.address, registers)
        except ModbusExceptionReply as exc:
            failure = exc
        finally:
            now = loop.time()
            code = write_status(failure, elapsed=now - started, write_timeout=unit.write_timeout,
                                link_up=unit.verdict(now).up)
            outcome = "ok" if failure is None else f"0x{failure.code:02X} {failure} ({code.value})"
            audit_write(unit.unit_id, 15 if point.bits else 16, point.table.value, point.address,
                        1 if point.bits else point.width, f"{outcome} (OPC UA write {point.node_id} = {value!r})")
            current_client.reset(token)
        if failure is not None:
            self.write_failures += 1
            log.warning("opcua: write %s = %r not applied: %s (%s)", point.node_id, value, failure, code.value)
        return _STATUS_CODES[code]

    # --- security -------------------------------------------------------------------------------

    def check_client(self, der: bytes) -> None:
        """Refuse a client certificate not in ``trusted_clients`` (Bad_SecurityChecksFailed): logged once with
        its thumbprint and written to ``rejected`` for an operator to move to ``trusted_clients``."""
        print_ = thumbprint(der)
        if print_ in self._trusted:
            return
        self._trusted = trusted_thumbprints(self.config.trusted_clients)  # one an operator has just moved there
        if print_ in self._trusted:
            log.info("opcua: client certificate %s is trusted now (found in %s)", print_, self.config.trusted_clients)
            return
        self.rejected_logins += 1
        if print_ not in self._rejected_logged:
            self._rejected_logged.add(print_)
            where = self.config.rejected_clients / f"{print_}.der"
            try:
                where.parent.mkdir(parents=True, exist_ok=True)
                where.write_bytes(der)
                saved = f"; written to {where}: move it to {self.config.trusted_clients} to trust it"
            except OSError as exc:
                saved = f" (not written to {where}: {exc})"
            log.warning("opcua: client certificate %s is not trusted: session refused%s", print_, saved)
        raise ServiceError(ua.StatusCodes.BadSecurityChecksFailed)

    def refuse_login(self, why: str) -> None:
        self.rejected_logins += 1
        log.warning("opcua: login refused: %s", why)

    # --- what is shown -------------------------------------------------------------------------

    def publish_rate(self) -> float:
        """Data changes handed to the subscriptions per second, over the last 10 s."""
        if len(self._rate) < 2:
            return 0.0
        (first, before), (last, after) = self._rate[0], self._rate[-1]
        return (after - before) / (last - first) if last > first else 0.0

    def counts(self) -> dict[str, int]:
        """Sessions, subscriptions and monitored items now."""
        server = self._server
        if server is None:
            return {"sessions": 0, "subscriptions": 0, "monitored_items": 0}
        iserver = server.iserver
        subscriptions = iserver.subscription_service.subscriptions
        bserver = server.bserver
        sessions = 0 if bserver is None else sum(
            1 for client in bserver.clients if client.processor is not None and client.processor.session is not None)
        return {
            "sessions": sessions,
            "subscriptions": len(subscriptions),
            "monitored_items": sum(len(sub.monitored_item_srv._monitored_items) for sub in subscriptions.values()),
        }
