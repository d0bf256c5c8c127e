"""Simulator factories of the ``sim://`` catalogue: ``plc5`` and a half-duplex line ``df1line``.

Listed in :mod:`gateway.sim.models` (``PLC5``, ``DF1LINE``) and in the DF1 link kind's ``simulators``:

* ``sim://plc5?checksum=bcc&drop=7&variant=typed_logical=accept`` - a PLC-5 on DF1 full duplex
  (:class:`~gateway.kinds.df1.sim.plc5.Plc5Simulator`; fault options as ``slc504``);
* ``sim://df1line?stations=1,2,3&dead=3&checksum=crc&corrupt=6&ignore=10&model=plc5&variant=reply_retries=3``
  - a multi-drop half-duplex line (:class:`~gateway.kinds.df1.sim.df1_multidrop.MultidropLine`; options in
  ``docs/develop/df1-half-duplex-line.md``).  Its variants (:data:`LINE_VARIANTS`) are the slave model's
  (``bad_frame_reply``, ``reply_retries``, ``duplicate_detect``, ``when_busy``), for every station,
  and ``typed_logical`` for ``model=plc5`` stations.  The line *paces itself* (:func:`self_paced`):
  it judges collisions on its own clock, so it is served without line settings (``paced=1`` is an
  error: give ``char_time=S``), and ``turnaround=S`` is the line's slave turnaround.
  Over TCP: ``serve_tcp(create_half_duplex_model("df1line", ...), host, port)``.
"""

from __future__ import annotations

from collections.abc import Mapping

from gateway.kinds.df1.sim.df1_half_duplex_slave import VARIANTS as SLAVE_VARIANTS
from gateway.kinds.df1.sim.df1_multidrop import MultidropLine
from gateway.kinds.df1.sim.plc5 import Plc5Simulator
from gateway.sim.variants import VariantTable, parse_variant_args, resolve_variants

__all__ = ["HALF_DUPLEX_MODELS", "LINE_VARIANTS", "create_half_duplex_model", "create_line", "create_plc5",
           "self_paced"]

HALF_DUPLEX_MODELS = ("plc5", "df1line")

#: The variants of ``sim://df1line``: the slave model's, and the PLC-5 controller's ``typed_logical``
#: (its other variants are of the full-duplex link, which a line station does not use).
LINE_VARIANTS: VariantTable = {**SLAVE_VARIANTS, "typed_logical": Plc5Simulator.VARIANTS["typed_logical"]}
_CONTROLLER_VARIANTS = ("typed_logical",)


def create_plc5(options: Mapping[str, str], *, ladder: bool = True,
                variants: Mapping[str, str] | None = None) -> Plc5Simulator:
    """``sim://plc5``: ValueError naming a bad option or variant."""
    return Plc5Simulator.from_options(options, ladder=ladder,
                                      variants=resolve_variants("plc5", Plc5Simulator.VARIANTS, variants or {}))


def create_line(options: Mapping[str, str], *, ladder: bool = True,
                variants: Mapping[str, str] | None = None) -> MultidropLine:
    """``sim://df1line``: ValueError naming a bad option or variant.

    ``variants`` may be every variant with its value (the catalogue resolves them first): a
    controller variant other than its default on a line of SLC stations is an error (no silent
    default reading), the default is fine.
    """
    values = resolve_variants("df1line", LINE_VARIANTS, variants or {})
    slave = {k: v for k, v in values.items() if k in SLAVE_VARIANTS}
    controller = {k: values[k] for k in _CONTROLLER_VARIANTS}
    if options.get("model", "slc504").strip().lower() != "plc5":
        chosen = sorted(k for k, v in controller.items() if v != LINE_VARIANTS[k][0])
        if chosen:
            raise ValueError(f"df1line: variant(s) {', '.join(chosen)} are of PLC-5 stations: "
                             "add model=plc5 or leave them out")
        controller = {}
    return MultidropLine.from_options(options, variants=slave, ladder=ladder, controller_variants=controller)


def create_half_duplex_model(
    model: str, options: Mapping[str, str], *, ladder: bool = True, variants_text: str = ""
) -> Plc5Simulator | MultidropLine:
    """A new ``plc5`` or ``df1line`` simulator; ValueError naming the bad option or variant."""
    chosen = parse_variant_args([variants_text])
    if model == "plc5":
        return create_plc5(options, ladder=ladder, variants=chosen)
    if model == "df1line":
        return create_line(options, ladder=ladder, variants=chosen)
    raise ValueError(f"unknown half-duplex simulator model {model!r} (models: {', '.join(HALF_DUPLEX_MODELS)})")


def self_paced(device: object) -> bool:
    """Whether ``device`` paces its own bytes (serve it without line settings)."""
    return bool(getattr(device, "self_paced", False))
