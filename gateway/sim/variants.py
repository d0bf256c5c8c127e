"""Controller variants: one switch for each reading of a manual that leaves behaviour open.

A simulator model declares its variants as a table ``name -> allowed values``; the first value
of each is the simulator's default reading.  They are chosen with ``--variant name=value`` on
``slc-gateway simulate`` and with ``variant=name=value`` in ``sim://`` URLs (repeat the key, or
separate several with commas).  ``docs/develop/controller-variants.md`` lists every variant with the
manual's words, its readings and what the driver does under each.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator, Mapping

__all__ = ["VariantTable", "pairwise_cover", "parse_variant_args", "resolve_variants", "variant_matrix"]

#: variant name -> allowed values (the first is the default reading)
VariantTable = Mapping[str, tuple[str, ...]]


def parse_variant_args(items: Iterable[str]) -> dict[str, str]:
    """``["a=b", "c=d,e=f"]`` -> ``{"a": "b", "c": "d", "e": "f"}``.  ValueError with a reason."""
    chosen: dict[str, str] = {}
    for item in items:
        for part in item.split(","):
            part = part.strip()
            if not part:
                continue
            name, sep, value = part.partition("=")
            name, value = name.strip(), value.strip()
            if not sep or not name or not value:
                raise ValueError(f"variant {part!r}: expected name=value")
            if name in chosen and chosen[name] != value:
                raise ValueError(f"variant {name!r} given twice ({chosen[name]!r} and {value!r})")
            chosen[name] = value
    return chosen


def resolve_variants(model: str, table: VariantTable, chosen: Mapping[str, str]) -> dict[str, str]:
    """Every variant of ``table`` with its value: the chosen one, else the default.

    An unknown name or value is a ValueError naming the choices, so a typo never silently
    simulates the default reading.
    """
    for name, value in chosen.items():
        if name not in table:
            known = ", ".join(sorted(table)) or "none"
            raise ValueError(f"{model}: unknown variant {name!r} (variants of {model}: {known})")
        if value not in table[name]:
            raise ValueError(f"{model}: variant {name}={value!r} is not one of {', '.join(table[name])}")
    return {name: chosen.get(name, values[0]) for name, values in table.items()}


def variant_matrix(table: VariantTable) -> Iterator[dict[str, str]]:
    """Every combination of every variant's values (for tests that cover all readings)."""
    names = sorted(table)
    for values in itertools.product(*(table[name] for name in names)):
        yield dict(zip(names, values, strict=True))


def pairwise_cover(table: VariantTable) -> list[dict[str, str]]:
    """Combinations in which every pair of values of two variants occurs at least once.

    Greedy (each pick covers the most pairs not yet covered), deterministic, and far smaller
    than :func:`variant_matrix` for tables of several variants: the quick run of a test over
    the matrix; the whole matrix runs in the long (``--soak``) run.
    """
    names = sorted(table)
    combos = list(variant_matrix(table))

    def pairs(combo: dict[str, str]) -> set[tuple[str, str, str, str]]:
        return {(a, combo[a], b, combo[b]) for i, a in enumerate(names) for b in names[i + 1 :]}

    uncovered = set().union(*(pairs(c) for c in combos)) if combos else set()
    chosen: list[dict[str, str]] = []
    while uncovered:
        best = max(combos, key=lambda c: len(pairs(c) & uncovered))
        chosen.append(best)
        uncovered -= pairs(best)
    if not chosen and combos:
        chosen.append(combos[0])  # one variant (or none): no pairs, one combination suffices
    if len(names) == 1:
        chosen = combos  # every value of the one variant
    return chosen
