"""The link kinds the config knows: one union of link models, and what is derived from it.

``LinkConfig`` is the one place that lists the link models (``LINK_MODELS`` and the protocol
tables are derived from it; no ``if protocol == ...`` anywhere). Each model's ``protocol`` field is a
one-value ``Literal``: pydantic picks the model by it (``Field(discriminator="protocol")``), so an
unknown protocol is an error naming the known ones, never a fallback to a default protocol, and each
model refuses the keys it does not have (``extra="forbid"``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, TypeAlias, get_args

from pydantic import Field, ValidationError, ValidatorFunctionWrapHandler, WrapValidator
from pydantic_core import InitErrorDetails

from gateway.config._common import Problems, check_port_url, sim_model
from gateway.config.df1 import Df1LinkConfig
from gateway.config.link import LinkBase
from gateway.config.slc_ascii import SlcAsciiLinkConfig

__all__ = [
    "LINK_MODELS",
    "PROTOCOL_DEFAULTS",
    "LinkConfig",
    "LinkProtocol",
    "TaggedLink",
    "link_model",
    "protocol_names",
    "protocol_of",
    "sim_model_names",
]

#: The type of one ``[[link]]``: the link model of one protocol. This union is the one list of the
#: link models (a union, not a tuple, so that mypy checks code that reads a link's keys); a new
#: protocol adds its model here.
LinkConfig: TypeAlias = SlcAsciiLinkConfig | Df1LinkConfig

#: Every link model, one per protocol, in the order of LinkConfig.
LINK_MODELS: tuple[type[LinkBase], ...] = get_args(LinkConfig)

#: A protocol name (the ``protocol`` key of a link); protocol_names() lists them.
LinkProtocol: TypeAlias = str


def protocol_of(model: type[LinkBase]) -> str:
    """The protocol name of a link model: the one value of its ``protocol`` Literal."""
    (name,) = get_args(model.model_fields["protocol"].annotation)
    return str(name)


_BY_PROTOCOL: Mapping[str, type[LinkBase]] = {protocol_of(model): model for model in LINK_MODELS}
_SIM_PROTOCOL: Mapping[str, str] = {
    model_name: protocol for protocol, model in _BY_PROTOCOL.items() for model_name in model.sim_models
}

#: Serial settings that depend on the protocol; filled in when a link does not give them.
PROTOCOL_DEFAULTS: Mapping[str, Mapping[str, object]] = {
    protocol: model.serial_defaults.as_keys() for protocol, model in _BY_PROTOCOL.items()
}


def protocol_names() -> tuple[str, ...]:
    """The protocols a link may name, in LINK_MODELS order."""
    return tuple(_BY_PROTOCOL)


def link_model(protocol: str) -> type[LinkBase] | None:
    """The link model of ``protocol`` (None: no such protocol)."""
    return _BY_PROTOCOL.get(protocol)


def sim_model_names() -> str:
    """``sim://slc150, sim://slc100 or sim://slc504``: the simulators, for messages."""
    names = [f"sim://{name}" for name in _SIM_PROTOCOL]
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else names[0]


def _simulator_problem(raw: object) -> str | None:
    """What is wrong with the simulator a raw ``[[link]]`` names in ``port`` (None: nothing).

    Read from the raw table, so that it is reported together with the link's other problems.
    A ``port`` of the wrong form is left to the link model's own check.
    """
    if not isinstance(raw, dict) or not isinstance(raw.get("port"), str):
        return None
    port, protocol = raw["port"], raw.get("protocol")
    try:
        check_port_url(port)
    except ValueError:
        return None
    model = sim_model(port)
    if model is None:
        return None
    speaks = _SIM_PROTOCOL.get(model)
    if speaks is None:
        return f"sim://{model}: no such simulator: expected {sim_model_names()}"
    if isinstance(protocol, str) and protocol in _BY_PROTOCOL and speaks != protocol:
        return f"sim://{model} simulates a controller that speaks {speaks}, but this link's protocol is {protocol}"
    return None


def _validate_link(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
    """Validate one ``[[link]]`` by its protocol's model, adding the check of its simulator."""
    problem = _simulator_problem(value)
    extra = [] if problem is None else [_port_error(value, problem)]
    try:
        link = handler(value)
    except ValidationError as exc:
        if not extra:
            raise
        errors = [
            InitErrorDetails(type=e["type"], loc=e["loc"], input=e["input"], ctx=e.get("ctx", {}))
            for e in exc.errors(include_url=False)
        ]
        raise ValidationError.from_exception_data(exc.title, [*errors, *extra]) from None
    if extra:
        raise ValidationError.from_exception_data("link", extra)
    return link


def _port_error(value: object, message: str) -> InitErrorDetails:
    return InitErrorDetails(type="value_error", loc=(), input=value, ctx={"error": Problems((("port",), message))})


#: One ``[[link]]`` as GatewayConfig validates it: the model chosen by ``protocol``, and the
#: simulator of its port checked against the simulators of every kind.
TaggedLink = Annotated[Annotated[LinkConfig, Field(discriminator="protocol")], WrapValidator(_validate_link)]
