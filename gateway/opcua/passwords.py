"""Password hashes for ``[[opcua.user]]``: salted scrypt (``slc-gateway hash-password``), or PBKDF2-SHA256.

``scrypt$<n>$<r>$<p>$<salt hex>$<hash hex>`` and ``pbkdf2-sha256$<iterations>$<salt hex>$<hash hex>``;
the password itself is never kept.  Checking compares in constant time.
"""

from __future__ import annotations

import hashlib
import hmac
import os
from typing import Final

__all__ = ["hash_password", "verify_password"]

#: scrypt's cost (2**14), block size and parallelism: about 16 MiB and 50 ms a check
_SCRYPT_N: Final = 2**14
_SCRYPT_R: Final = 8
_SCRYPT_P: Final = 1
_SALT_BYTES: Final = 16
_HASH_BYTES: Final = 32


def hash_password(password: str, *, salt: bytes | None = None) -> str:
    """A salted scrypt hash of ``password`` in the form the config takes."""
    salt = os.urandom(_SALT_BYTES) if salt is None else salt
    digest = hashlib.scrypt(password.encode(), salt=salt, n=_SCRYPT_N, r=_SCRYPT_R, p=_SCRYPT_P, dklen=_HASH_BYTES)
    return f"scrypt${_SCRYPT_N}${_SCRYPT_R}${_SCRYPT_P}${salt.hex()}${digest.hex()}"


def verify_password(password: str, stored: str) -> bool:
    """Whether ``password`` is the one ``stored`` was made from (False for a malformed hash)."""
    parts = stored.split("$")
    try:
        if parts[0] == "scrypt" and len(parts) == 6:
            n, r, p = int(parts[1]), int(parts[2]), int(parts[3])
            salt, expected = bytes.fromhex(parts[4]), bytes.fromhex(parts[5])
            digest = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=len(expected),
                                    maxmem=256 * n * r + 1024 * 1024)
        elif parts[0] == "pbkdf2-sha256" and len(parts) == 4:
            salt, expected = bytes.fromhex(parts[2]), bytes.fromhex(parts[3])
            digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, int(parts[1]), len(expected))
        else:
            return False
    except (ValueError, MemoryError):
        return False
    return hmac.compare_digest(digest, expected)
