"""The configuration file: TOML text -> validated, frozen config objects.

``load_config(path)`` and ``parse_config(text)`` return a :class:`GatewayConfig` or raise ONE
:class:`~gateway.errors.ConfigError` that lists every problem found, each with the file, the line
(where it can be found), the key path in TOML terms and what is wrong::

    plant.toml: 2 errors in the configuration:
      plant.toml:14: link "press-1" (link[0]).timeout: must be greater than 0 (got -1)
      plant.toml:23: link "press-2" (link[1]).map[0].count: missing required key

Indexes in key paths count from 0: ``link[1]`` is the second ``[[link]]`` table of the file.

The models are pydantic v2 models (frozen, unknown keys forbidden, strict types: TOML is typed, so
``unit = "1"`` is an error, not a conversion). Values a consumer needs are resolved here: the
per-protocol serial defaults are filled in, paths are made absolute (relative to the directory of
the config file), ``listen`` strings are normalised and ``writable`` ranges and ``allow`` networks
are parsed. ``GatewayConfig.describe()`` prints every key with its effective value, as TOML that
loads back to the same configuration (except credentials in port URLs, shown as ``***``), and
``GatewayConfig.warnings()`` lists valid settings that are probably not what was meant.

The modules, each one concern:

* ``schema``: the sections and the whole file (:class:`GatewayConfig`);
* ``link``: the keys every ``[[link]]`` has (:class:`LinkBase`); each link kind's package
  (``gateway/kinds/<kind>/config.py``) has its model, with its serial defaults and its own keys;
  ``links``: the discriminated union on ``protocol`` of the models of the registered link kinds
  (:mod:`gateway.kinds`);
* ``reporting``: pydantic errors -> one ConfigError with key paths, lines and suggestions;
  ``lines``: the line index of the TOML text;
* ``writer``: the resolved-config writer (``check-config``'s output);
* ``loader``: reading and parsing the file; ``_common``: what the others share.
"""

from __future__ import annotations

from gateway.config._common import parse_listen
from gateway.config.link import LinkBase, SerialDefaults, WritableRange, WritableTable
from gateway.config.links import LinkConfig, LinkProtocol, link_models, protocol_defaults, protocol_names
from gateway.config.loader import MAX_CONFIG_BYTES, load_config, load_config_file, parse_config
from gateway.config.schema import GatewayConfig, LoggingConfig, MetricsConfig, ModbusConfig, TlsConfig

__all__ = [
    "MAX_CONFIG_BYTES",
    "GatewayConfig",
    "LinkBase",
    "LinkConfig",
    "LinkProtocol",
    "LoggingConfig",
    "MetricsConfig",
    "ModbusConfig",
    "SerialDefaults",
    "TlsConfig",
    "WritableRange",
    "WritableTable",
    "link_models",
    "load_config",
    "load_config_file",
    "parse_config",
    "parse_listen",
    "protocol_defaults",
    "protocol_names",
]
