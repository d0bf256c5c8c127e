"""Simulator factories for the ``sim://`` registry: ``plc5`` and a half-duplex line ``df1line`` (issue #12).

For ``gateway.sim.create_simulator`` (the registry's owner wires them)::

    if model in HALF_DUPLEX_MODELS:
        return create_half_duplex_model(model, fault_options, ladder=ladder, variants_text=options.get("variant", ""))

and in ``open_sim_stream``: a self-paced device (:func:`self_paced`) is served **without** line
settings (the line judges collisions on its own clock; ``paced`` is ignored for it).

* ``sim://plc5?checksum=bcc&drop=7&variant=typed_logical=accept`` - a PLC-5 on DF1 full duplex
  (:class:`~gateway.sim.plc5.Plc5Simulator`; fault options as ``slc504``);
* ``sim://df1line?stations=1,2,3&dead=3&checksum=crc&corrupt=6&ignore=10&model=plc5&variant=reply_retries=3``
  - a multi-drop half-duplex line (:class:`~gateway.sim.df1_multidrop.MultidropLine`; options in
  ``docs/df1-half-duplex-line.md``).  ``variant=`` takes the slave model's variants
  (``bad_frame_reply``, ``reply_retries``, ``duplicate_detect``, ``when_busy``) and the stations'
  controller variants (``typed_logical`` when ``model=plc5``, the SLC 5/04's otherwise), told apart
  by name.  Over TCP: ``serve_tcp(create_half_duplex_model("df1line", ...), host, port)``.
"""

from __future__ import annotations

from collections.abc import Mapping

from gateway.sim.df1_half_duplex_slave import VARIANTS as SLAVE_VARIANTS
from gateway.sim.df1_multidrop import MultidropLine
from gateway.sim.plc5 import Plc5Simulator
from gateway.sim.slc500 import Slc500Simulator
from gateway.sim.variants import parse_variant_args, resolve_variants

__all__ = ["HALF_DUPLEX_MODELS", "create_half_duplex_model", "self_paced"]

HALF_DUPLEX_MODELS = ("plc5", "df1line")


def create_half_duplex_model(
    model: str, options: Mapping[str, str], *, ladder: bool = True, variants_text: str = ""
) -> Plc5Simulator | MultidropLine:
    """A new ``plc5`` or ``df1line`` simulator; ValueError naming the bad option or variant."""
    chosen = parse_variant_args([variants_text])
    if model == "plc5":
        variants = resolve_variants(model, Plc5Simulator.VARIANTS, chosen)
        return Plc5Simulator.from_options(options, ladder=ladder, variants=variants)
    if model != "df1line":
        raise ValueError(f"unknown half-duplex simulator model {model!r} (models: {', '.join(HALF_DUPLEX_MODELS)})")
    controller_table = Plc5Simulator.VARIANTS if options.get("model", "slc504") == "plc5" else Slc500Simulator.VARIANTS
    slave = {k: v for k, v in chosen.items() if k in SLAVE_VARIANTS}
    controller = {k: v for k, v in chosen.items() if k not in SLAVE_VARIANTS}
    unknown = sorted(set(controller) - set(controller_table))
    if unknown:
        known = ", ".join(sorted(set(SLAVE_VARIANTS) | set(controller_table)))
        raise ValueError(f"df1line: unknown variant(s) {', '.join(unknown)} (variants of df1line: {known})")
    return MultidropLine.from_options(
        options,
        variants=resolve_variants("df1line", SLAVE_VARIANTS, slave),
        ladder=ladder,
        controller_variants=resolve_variants("df1line", controller_table, controller),
    )


def self_paced(device: object) -> bool:
    """Whether ``device`` paces its own bytes (serve it without line settings)."""
    return isinstance(device, MultidropLine)
