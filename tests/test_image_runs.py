"""``gateway.image._strided_runs``: the runs the register images decode blocks with.

The image decodes a block with one slice copy per run of registers whose index and source bytes
advance evenly; a wrong run writes a register from the wrong byte.  Its contract (docstring):
the runs, expanded, are exactly the items, with positive steps; an even progression is one run.
"""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from gateway.image import _strided_runs

Item = tuple[int, tuple[int, ...]]


def expand(runs: list[tuple[int, int, int, tuple[int, ...], int]]) -> list[Item]:
    out: list[Item] = []
    for first, step, n, src, src_step in runs:
        assert step > 0 and src_step > 0 and n >= 1
        out += [(first + k * step, tuple(s + k * src_step if s >= 0 else s for s in src)) for k in range(n)]
    return out


@st.composite
def items(draw: st.DrawFn) -> list[Item]:
    width = draw(st.integers(1, 2))
    indexes = sorted(draw(st.sets(st.integers(0, 60), min_size=1, max_size=25)))
    source = st.sampled_from([-1]) | st.integers(0, 120)
    return [(i, tuple(draw(source) for _ in range(width))) for i in indexes]


@given(items())
def test_the_runs_are_exactly_the_items(given_items: list[Item]) -> None:
    assert expand(_strided_runs(given_items)) == given_items


@given(first=st.integers(0, 20), step=st.integers(1, 5), n=st.integers(2, 20), src=st.integers(0, 50),
       src_step=st.integers(1, 4), msb_missing=st.booleans())
def test_an_even_progression_is_one_run(first: int, step: int, n: int, src: int, src_step: int,
                                        msb_missing: bool) -> None:
    progression = [(first + k * step, (-1 if msb_missing else src + 1 + k * src_step, src + k * src_step))
                   for k in range(n)]
    assert _strided_runs(progression) == [(first, step, n, progression[0][1], src_step)]


def test_a_progression_broken_by_a_step_or_a_missing_byte_starts_a_new_run() -> None:
    assert len(_strided_runs([(0, (0,)), (1, (2,)), (2, (4,)), (4, (6,))])) == 2  # index step changes
    assert len(_strided_runs([(0, (0, 1)), (1, (2, 3)), (2, (-1, 5))])) == 2  # MSB source disappears
    assert len(_strided_runs([(0, (5,)), (1, (4,))])) == 2  # sources go back: no negative steps
    assert len(_strided_runs([(0, (0, 1)), (1, (2, 4))])) == 2  # the two sources advance unevenly
