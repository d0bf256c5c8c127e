"""Controller simulators, written from the manuals, with fault injection.

``sim://MODEL[?options]`` URLs open an in-process simulator.  The models are listed in
:mod:`gateway.sim.models` (built in: ``slc150``, ``slc100``, ``slc504``, ``plc5`` and the DF1
half-duplex multi-drop line ``df1line``; a link kind may add its own).  Options:

=====================  ==========================================================================
``garble=N``           corrupt 1 in N replies
``drop=N``             drop 1 in N replies
``delay=S``            add S seconds to every reply
``power_cycle_every``  (SLC 100/150) power-cycle before every N-th command
``fault_every=N``      (SLC 100/150) emit ``;T`` after every N-th command
``seed=N``             seed of the fault generator (reproducible runs)
``ladder=0``           freeze the ladder (values change only when written)
``paced=1``            pace every character at the link's baud rate (a real line's speed)
``turnaround=S``       controller turnaround before each reply, seconds (with or without pacing)
``scan=S``             the controller's program scan, seconds (``scan=0.02-0.06``: varying): every
                       answer at the end of the scan in progress, at most 0.3 s (``gateway.sim.scan``;
                       every model, ``df1line`` per station)
``instance=NAME``      a separate controller for each name (default: one per URL)
``variant=NAME=VALUE``  a reading of the manual where it leaves behaviour open (repeat the key,
                       or separate several with commas); see ``docs/develop/controller-variants.md``
=====================  ==========================================================================

A *self-paced* model (``df1line``: ``sim://df1line?stations=1,2,3&dead=3&corrupt=6&ignore=10``, its
options in ``docs/develop/df1-half-duplex-line.md``) judges collisions on its own clock: it takes
``char_time=S`` instead of ``paced=1`` (an error for it), and ``turnaround=S`` is its own option.

The same URL always reaches the same simulated controller (or line) within a process, so a reconnecting
driver finds the controller as it left it, and tests can inspect it with ``get_simulator(url)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from gateway.errors import LinkDown
from gateway.sim.models import sim_models
from gateway.sim.serve import SimDevice, SimStream
from gateway.sim.variants import parse_variant_args, resolve_variants
from gateway.streams import SerialSettings

__all__ = [
    "create_simulator",
    "get_simulator",
    "model_names",
    "open_sim_stream",
    "parse_sim_url",
    "reset_simulators",
    "variants_of",
]

_STREAM_OPTIONS = ("paced", "turnaround", "instance", "ladder", "variant")
#: a self-paced device takes ``turnaround`` itself (and refuses ``paced``)
_SELF_PACED_STREAM_OPTIONS = ("instance", "ladder", "variant")
_registry: dict[str, Any] = {}


def _truthy(text: str) -> bool:
    return text.strip().lower() not in ("0", "false", "no", "")


def parse_sim_url(url: str) -> tuple[str, dict[str, str]]:
    """``sim://slc150?drop=7`` -> ("slc150", {"drop": "7"}).  Raises ValueError with a reason."""
    parts = urlsplit(url)
    if parts.scheme != "sim":
        raise ValueError(f"{url}: not a sim:// URL")
    model = (parts.netloc or parts.path.lstrip("/")).lower()
    if model not in sim_models():
        raise ValueError(f"{url}: unknown simulator {model!r} (choose from {', '.join(model_names())})")
    options: dict[str, str] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key == "variant" and options.get(key):
            options[key] += "," + value  # repeatable: every variant counts, not only the last
        else:
            options[key] = value
    if sim_models()[model].self_paced and _truthy(options.get("paced", "0")):
        raise ValueError(f"{url}: sim://{model} paces itself: give char_time=S (seconds per character) "
                         "instead of paced=1")
    if options.get("variant"):
        # validate now: a typo is an error, never a silent default reading
        variants_of(model, parse_variant_args([options["variant"]]))
    return model, options


def model_names() -> tuple[str, ...]:
    """The simulator models, built-in ones first."""
    names = tuple(sim_models())
    if not names:
        # the kinds' models are registered by the registry of kinds, imported by every entry point
        raise RuntimeError("no sim:// models are registered: import gateway.kinds before opening a simulator")
    return names


def variants_of(model: str, chosen: Mapping[str, str]) -> dict[str, str]:
    """Every variant of ``model`` with its value (chosen or default); ValueError naming the choices."""
    return resolve_variants(model, sim_models()[model].variants(), chosen)


def create_simulator(model: str, options: dict[str, str]) -> SimDevice:
    """A new simulated controller.  ``options`` are the fault/ladder options (see module doc)."""
    found = sim_models().get(model)
    if found is None:
        raise ValueError(f"unknown simulator {model!r} (choose from {', '.join(model_names())})")
    stream_options = _SELF_PACED_STREAM_OPTIONS if found.self_paced else _STREAM_OPTIONS
    fault_options = {k: v for k, v in options.items() if k not in stream_options}
    ladder = options.get("ladder", "1") not in ("0", "false", "no")
    variants = variants_of(model, parse_variant_args([options.get("variant", "")]))
    return found.create(fault_options, ladder, variants)


def get_simulator(url: str) -> Any:
    """The in-process simulator behind ``url`` (created on first use)."""
    device = _registry.get(url)
    if device is None:
        model, options = parse_sim_url(url)
        device = create_simulator(model, options)
        _registry[url] = device
    return device


def reset_simulators() -> None:
    """Forget every in-process simulator (tests)."""
    _registry.clear()


def open_sim_stream(url: str, settings: SerialSettings) -> SimStream:
    try:
        model, options = parse_sim_url(url)
        device = get_simulator(url)
        if sim_models()[model].self_paced:
            return SimStream(device)  # its own clock: no line settings, its turnaround is its option
        turnaround = float(options.get("turnaround", "0") or 0)
    except ValueError as exc:
        raise LinkDown(str(exc)) from exc
    paced = _truthy(options.get("paced", "0"))
    return SimStream(device, settings if paced else None, turnaround)
