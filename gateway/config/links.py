"""The link kinds the config knows, from the registry of link kinds (:mod:`gateway.kinds`).

A ``[[link]]`` is validated by the model of its ``protocol``: the discriminated union
(``Field(discriminator="protocol")``) of the config models of every registered kind, rebuilt
when a kind is registered, so that a kind registered from outside is accepted like a built-in
one.  Each model's ``protocol`` field is a one-value ``Literal``: an unknown protocol is an error
naming the known ones, never a fallback to a default protocol, and each model refuses the keys
it does not have (``extra="forbid"``).

The config does not import the registry (the kinds' packages import the config models, so that
would be a circle): the registry passes itself in when it is imported
(:func:`use_link_kinds`, called by :mod:`gateway.kinds`), and it is read when a config is
validated, so that a kind registered later is seen.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Annotated, Any, TypeAlias, Union

from pydantic import (
    Field,
    SerializeAsAny,
    TypeAdapter,
    ValidationError,
    ValidationInfo,
    ValidatorFunctionWrapHandler,
    WrapValidator,
)
from pydantic_core import InitErrorDetails

from gateway.config._common import Problems, check_port_url, sim_model
from gateway.config.link import LinkBase, protocol_of

__all__ = [
    "LinkConfig",
    "LinkProtocol",
    "TaggedLink",
    "link_model",
    "link_models",
    "protocol_defaults",
    "protocol_names",
    "protocol_of",
    "sim_model_names",
    "use_link_kinds",
]

#: The type of one ``[[link]]``: the link model of one protocol (a LinkBase subclass).
LinkConfig: TypeAlias = LinkBase

#: A protocol name (the ``protocol`` key of a link); protocol_names() lists them.
LinkProtocol: TypeAlias = str


#: The registry's config models by protocol, as :func:`use_link_kinds` was given them.
_registry: list[Callable[[], Mapping[str, type[LinkBase]]]] = []


def use_link_kinds(models: Callable[[], Mapping[str, type[LinkBase]]]) -> None:
    """Validate ``[[link]]`` tables by ``models()``: protocol -> config model, built-in ones first.

    Called once by the registry of link kinds (:mod:`gateway.kinds`) when it is imported;
    ``models`` is called at every validation, so that kinds registered later are seen.
    """
    _registry[:] = [models]


def _by_protocol() -> Mapping[str, type[LinkBase]]:
    if not _registry:
        raise RuntimeError("no link kinds are known to the config: import gateway.kinds before validating a config")
    return _registry[0]()


def link_models() -> tuple[type[LinkBase], ...]:
    """Every link model, one per registered kind, built-in ones first."""
    return tuple(_by_protocol().values())


def protocol_names() -> tuple[str, ...]:
    """The protocols a link may name, built-in ones first."""
    return tuple(_by_protocol())


def link_model(protocol: str) -> type[LinkBase] | None:
    """The link model of ``protocol`` (None: no such protocol)."""
    return _by_protocol().get(protocol)


def protocol_defaults() -> dict[str, dict[str, object]]:
    """Serial settings that depend on the protocol (filled in when a link does not give them)."""
    return {protocol: model.serial_defaults.as_keys() for protocol, model in _by_protocol().items()}


def _sim_protocols() -> dict[str, str]:
    return {name: protocol for protocol, model in _by_protocol().items() for name in model.sim_models}


def sim_model_names() -> str:
    """``sim://slc150, sim://slc100 or sim://slc504``: the simulators, for messages."""
    names = [f"sim://{name}" for name in _sim_protocols()]
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
    speaks = _sim_protocols().get(model)
    if speaks is None:
        return f"sim://{model}: no such simulator: expected {sim_model_names()}"
    if isinstance(protocol, str) and protocol in _by_protocol() and speaks != protocol:
        return f"sim://{model} simulates a controller that speaks {speaks}, but this link's protocol is {protocol}"
    return None


_adapters: dict[tuple[type[LinkBase], ...], TypeAdapter[Any]] = {}


def _adapter() -> TypeAdapter[Any]:
    """The discriminated union of the registered kinds' models (one adapter per set of models)."""
    models = link_models()
    adapter = _adapters.get(models)
    if adapter is None:
        form: Any = models[0]
        if len(models) > 1:
            union: Any = Union[models]  # noqa: UP007 - built at run time from the registry
            form = Annotated[union, Field(discriminator="protocol")]
        adapter = TypeAdapter(form)
        _adapters[models] = adapter
    return adapter


def _validate_link(value: Any, handler: ValidatorFunctionWrapHandler, info: ValidationInfo) -> Any:
    """Validate one ``[[link]]`` by its protocol's model, adding the check of its simulator."""
    if isinstance(value, LinkBase):
        return value
    problem = _simulator_problem(value)
    extra = [] if problem is None else [_port_error(value, problem)]
    try:
        link = _adapter().validate_python(value, context=info.context)
    except ValidationError as exc:
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


#: One ``[[link]]`` as GatewayConfig validates it: the model chosen by ``protocol`` among the
#: registered kinds' models, and the simulator of its port checked against every kind's simulators.
TaggedLink = Annotated[SerializeAsAny[LinkBase], WrapValidator(_validate_link)]
