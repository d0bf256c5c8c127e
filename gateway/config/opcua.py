"""``[opcua]``: the gateway as an OPC UA server (off when the section is absent; docs/guide/opcua.md).

The endpoint URL is ``opc.tcp://host:port``: the server listens on that host and port, and the host
part is what clients are told in the endpoint descriptions.  ``security`` names the endpoints
offered (OPC UA Part 7 security policies with their message security mode); ``[[opcua.user]]``
the user names that may log in, each with a salted hash of its password (``slc-gateway
hash-password``) and a role.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final, Literal
from urllib.parse import urlsplit

from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.config._common import Model, Problems, show

__all__ = ["OPCUA_SECURITY", "OpcUaConfig", "OpcUaUser"]

#: the endpoints the server can offer: "None" (no security) and Basic256Sha256 signed, or signed and encrypted
OPCUA_SECURITY: Final = ("None", "Basic256Sha256-Sign", "Basic256Sha256-SignAndEncrypt")
_HASH_SCHEMES: Final = ("scrypt$", "pbkdf2-sha256$")


def _config_path(value: object, info: ValidationInfo) -> Path:
    """A path of the section, absolute against the config file's directory (it need not exist yet)."""
    if isinstance(value, Path):
        value = str(value)
    if not isinstance(value, str) or not value.strip() or "\0" in value:
        raise ValueError(f"{show(value)} is not a path")
    path = Path(value)
    base = info.context.get("base_dir") if isinstance(info.context, dict) else None
    return path if path.is_absolute() else Path(base if isinstance(base, (str, Path)) else Path.cwd()) / path


class OpcUaUser(Model):
    """``[[opcua.user]]``: a user name that may open a session with a password."""

    name: str = Field(min_length=1, max_length=64)
    """The user name the client gives."""
    password_hash: str
    """The password's salted hash, from `slc-gateway hash-password` (scrypt or PBKDF2-SHA256); never the password."""
    role: Literal["read", "write"] = "read"
    """read: browse, read and subscribe; write: also write the points that are writable."""

    @field_validator("password_hash")
    @classmethod
    def _check_hash(cls, value: str) -> str:
        if not value.startswith(_HASH_SCHEMES) or value.count("$") < 2:
            raise ValueError("not a password hash: make one with `slc-gateway hash-password` (it reads the "
                             "password on standard input)")
        return value


class OpcUaConfig(Model):
    """``[opcua]``."""

    listen: str = "opc.tcp://0.0.0.0:4840"
    """The endpoint URL, opc.tcp://host:port: the server listens there, and the host part is what clients are told
    (give the name or address clients reach the gateway by)."""
    security: tuple[Literal["None", "Basic256Sha256-Sign", "Basic256Sha256-SignAndEncrypt"], ...] = Field(
        ("None", "Basic256Sha256-SignAndEncrypt"), strict=False, min_length=1)
    """The endpoints offered: "None", "Basic256Sha256-Sign", "Basic256Sha256-SignAndEncrypt"."""
    certificate: Path = Field(Path("opcua/cert.der"), validate_default=True)
    """The server's certificate (DER); generated, self-signed for this host's name, when absent (relative: to the
    config file's directory)."""
    private_key: Path = Field(Path("opcua/key.pem"), validate_default=True)
    """The private key of certificate (PEM); generated with it when absent."""
    trusted_clients: Path = Field(Path("opcua/trusted"), validate_default=True)
    """A directory of client certificates (DER or PEM) accepted on the Sign and SignAndEncrypt endpoints; a client
    refused is written to the directory rejected beside it (opcua/rejected), from where an operator may move it
    here (read at start)."""
    anonymous: Literal["none", "read"] = "read"
    """Anonymous sessions: "read" (browse, read, subscribe) or "none" (refused: every client logs in as a user)."""
    user: tuple[OpcUaUser, ...] = Field((), strict=False)
    """[[opcua.user]]: the users that log in with a name and password."""
    publish_interval: float = Field(0.1, gt=0, le=10)
    """Seconds between the server's passes over the images for monitored items (at least; half the shortest
    publishing interval of the subscriptions when that is longer, at most 0.5 s): what was read meanwhile is
    published in that pass, and a monitored item's sampling interval is never shorter."""

    @field_validator("listen")
    @classmethod
    def _check_listen(cls, value: str) -> str:
        parts = urlsplit(value)
        if parts.scheme != "opc.tcp" or not parts.hostname:
            raise ValueError(f"{show(value)}: the endpoint URL is opc.tcp://host:port")
        try:
            parts.port  # noqa: B018 (raises on a bad port)
        except ValueError:
            raise ValueError(f"{show(value)}: the port must be 0..65535") from None
        return value

    @field_validator("certificate", "private_key", "trusted_clients", mode="before")
    @classmethod
    def _path(cls, value: object, info: ValidationInfo) -> Path:
        return _config_path(value, info)

    @model_validator(mode="after")
    def _check(self) -> OpcUaConfig:
        names = [user.name for user in self.user]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise Problems((("user",), f"user names given twice: {', '.join(twice)}"))
        if len(set(self.security)) != len(self.security):
            raise Problems((("security",), "an endpoint is given twice"))
        return self

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` of the endpoint URL (port 4840 when left out)."""
        parts = urlsplit(self.listen)
        return parts.hostname or "", 4840 if parts.port is None else parts.port

    @property
    def rejected_clients(self) -> Path:
        """Where refused client certificates are written: ``rejected`` beside ``trusted_clients``."""
        return self.trusted_clients.parent / "rejected"

    @property
    def writers(self) -> tuple[str, ...]:
        """The users with the write role."""
        return tuple(user.name for user in self.user if user.role == "write")
