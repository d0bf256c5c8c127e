"""A config reload that changes the links while the Sparkplug edge node publishes them.

The node's devices and their metrics are the units'; a reload that starts or stops a line ends the
node's MQTT session (NDEATH with its bdSeq) and births the devices as they now are in a new session
(the next bdSeq): Sparkplug 3.0 §5.4 (a new session, a new bdSeq) and the birth certificate as the
whole set of metrics.  The independent host application (``tests/peers/sparkplug_host.py``) checks
every message; a reload that changes no line leaves the session alone.
"""

from __future__ import annotations

from pathlib import Path

from mosquitto_support import Broker, broker  # noqa: F401 (the fixture)
from test_sparkplug_gateway import GROUP, NODE, Plant, config_text, kind, link_text, plant, value  # noqa: F401

from gateway.app import Gateway
from gateway.config import parse_config


async def test_a_link_added_by_reload_is_born_in_a_new_session(plant: Plant, tmp_path: Path) -> None:  # noqa: F811
    async with Gateway(plant.config()) as gw:
        nbirth = await plant.wait(kind("NBIRTH"))
        await plant.wait(kind("DBIRTH", "oven"))
        first = nbirth.metric("bdSeq").value
        count = len(plant.host.messages)
        # the same file with the oven's link under a new name: its line restarts, the press's is kept
        links = link_text("press", 1, plant.press) + link_text("kiln", 2, plant.oven, read_only=True)
        assert await gw.apply(parse_config(config_text(plant.broker.port, plant.state_file, links)))
        ndeath = await plant.wait(kind("NDEATH"), since=count)
        assert ndeath.metric("bdSeq").value == first
        reborn = await plant.wait(kind("NBIRTH"), since=count)
        assert reborn.metric("bdSeq").value == (first + 1) % 256
        await plant.wait(kind("DBIRTH", "kiln"), since=reborn.index)
        await plant.wait(kind("DBIRTH", "press"), since=reborn.index)
        # the initial table of the simulator (docs/develop/controller-variants.md): N7:n = n
        await plant.wait(lambda m: value(plant, "kiln", "N7:2").value == 2, 10)
        assert not any(m.device_id == "oven" and m.message_type == "DBIRTH" for m in plant.host.messages[reborn.index:])
        # a reload that changes no line keeps the session
        count = len(plant.host.messages)
        assert await gw.apply(parse_config(config_text(plant.broker.port, plant.state_file, links)))
        await plant.wait(kind("DDATA", "press"), since=count)
        assert not any(m.message_type in ("NDEATH", "NBIRTH") for m in plant.host.messages[count:])


async def test_a_reload_that_only_removes_a_link_ends_the_session_and_its_device_is_not_born_again(
        plant: Plant) -> None:  # noqa: F811
    """No line starts, one stops: the births of the node are its devices, so the session still ends
    (NDEATH) and the new one's births are without the removed device (a DCMD to it would go nowhere)."""
    async with Gateway(plant.config()) as gw:
        nbirth = await plant.wait(kind("NBIRTH"))
        await plant.wait(kind("DBIRTH", "oven"))
        await plant.wait(kind("DBIRTH", "press"))
        first = nbirth.metric("bdSeq").value
        count = len(plant.host.messages)
        links = link_text("press", 1, plant.press)  # the oven's link removed, nothing added
        assert await gw.apply(parse_config(config_text(plant.broker.port, plant.state_file, links)))
        assert [device.name for device in gw.sparkplug.devices] == ["press"]  # type: ignore[union-attr]
        ndeath = await plant.wait(kind("NDEATH"), since=count)
        assert ndeath.metric("bdSeq").value == first
        reborn = await plant.wait(kind("NBIRTH"), since=count)
        assert reborn.metric("bdSeq").value == (first + 1) % 256
        await plant.wait(kind("DBIRTH", "press"), since=reborn.index)
        # the next pass of the node (a DDATA of the press) comes after every birth of the new session
        await plant.wait(kind("DDATA", "press"), since=reborn.index)
        assert not any(m.device_id == "oven" for m in plant.host.messages[reborn.index:])
