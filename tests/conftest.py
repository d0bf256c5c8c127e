"""Options shared by the whole test suite."""

from __future__ import annotations

import pytest
from hypothesis import Phase, settings

# The built-in kinds register their sim:// models when the registry is imported (the app, the CLI
# and the tools import it); tests that open simulators directly need them too.
import gateway.kinds  # noqa: F401

# `make mutation` runs the tests with --hypothesis-profile=mutation: the same examples for every
# mutant (derandomize, no example database) and no shrinking (a mutant is killed by the first
# failure; nobody reads the minimal example).
settings.register_profile(
    "mutation", derandomize=True, database=None, phases=[Phase.explicit, Phase.generate], print_blob=False
)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--soak",
        action="store_true",
        default=False,
        help="run the long fault soak in tests/soak (10+ minutes) instead of its quick mode",
    )
