"""The variant switches' parsing: a typo never silently simulates the default reading."""

import pytest

from gateway.sim.variants import parse_variant_args, resolve_variants, variant_matrix

TABLE = {"power_up_id": ("zero", "retained"), "z_after_power_up": ("silent", "error")}


def test_parse_variant_args_accepts_repeats_and_commas() -> None:
    assert parse_variant_args(["power_up_id=retained", "z_after_power_up=error, "]) == {
        "power_up_id": "retained",
        "z_after_power_up": "error",
    }
    assert parse_variant_args(["a=1,b=2"]) == {"a": "1", "b": "2"}


@pytest.mark.parametrize("bad", ["power_up_id", "=x", "a=", "a=1,a=2"])
def test_parse_variant_args_refuses_malformed(bad: str) -> None:
    with pytest.raises(ValueError):
        parse_variant_args([bad])


def test_resolve_fills_defaults_and_names_choices() -> None:
    assert resolve_variants("slc150", TABLE, {"power_up_id": "retained"}) == {
        "power_up_id": "retained",
        "z_after_power_up": "silent",
    }
    with pytest.raises(ValueError, match="variants of slc150: power_up_id, z_after_power_up"):
        resolve_variants("slc150", TABLE, {"power_up": "retained"})
    with pytest.raises(ValueError, match="not one of zero, retained"):
        resolve_variants("slc150", TABLE, {"power_up_id": "kept"})


def test_variant_matrix_covers_every_combination() -> None:
    combos = list(variant_matrix(TABLE))
    assert len(combos) == 4
    assert {(c["power_up_id"], c["z_after_power_up"]) for c in combos} == {
        ("zero", "silent"), ("zero", "error"), ("retained", "silent"), ("retained", "error"),
    }


def test_pairwise_cover_covers_every_pair_with_fewer_combinations() -> None:
    from gateway.sim.variants import pairwise_cover

    table = {"a": ("1", "2"), "b": ("x", "y", "z"), "c": ("p", "q"), "d": ("m", "n")}
    cover = pairwise_cover(table)
    assert len(cover) < len(list(variant_matrix(table)))
    names = sorted(table)
    for i, first in enumerate(names):
        for second in names[i + 1 :]:
            for u in table[first]:
                for v in table[second]:
                    assert any(c[first] == u and c[second] == v for c in cover), (first, u, second, v)
    assert pairwise_cover({"a": ("1", "2", "3")}) == [{"a": "1"}, {"a": "2"}, {"a": "3"}]
