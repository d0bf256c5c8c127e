"""Plan quality: bytes on the wire per scan of ``plan_df1`` against an independent optimum.

For random realistic SLC 5/04 maps (scattered N7, N10, B3 bits, T4 / C5 accumulators, F8 floats;
one entry = a run of consecutive values; half the maps "dense": many short N7 runs over N7:0-139,
where merging and the read size limit matter) the DF1 planner's read plan is costed in *bytes on the
wire per scan*: for every block, the command frame, the controller's DLE ACK, the reply frame
and our DLE ACK, built with the protocol encoders (CRC; DLE doubling of the header and address
bytes included - an element number 16 is sent as DLE DLE; elements >= 255 take a 3-byte field).
Reply data are costed as zeros (their DLE doubling depends on the values).

The optimum is found independently of ``gateway.kinds.df1.plan``:

* the needed words are computed here from the entries (N: word k; F: words 2k, 2k+1; T/C .ACC:
  word 3k+2; B bits: word bit//16);
* *exhaustive*: every way to cut each file's sorted needed spans into consecutive groups
  (2^(n-1) ways, for files with n <= 14 spans), each group read by one block from the element boundary
  at or before its first word to its last word, within the read size limit - an optimal cover
  always has this form, since a block's cost only grows with its length;
* *DP over word positions* (every block start on an element boundary and every end, not just
  those at needed words) as a cross-check, which also covers larger maps.

Both use the same start-on-an-element-boundary rule as the planner.  A second optimum lets a
block start at any word (a sub-element start: ``T4:3.ACC``), to show what that rule costs.

    python bench/plan_quality.py [--quick] [--maps N] [--seed S]
"""

from __future__ import annotations

import argparse
import functools
import itertools
import random
import statistics

from _benchlib import print_machine, result, table

from gateway.kinds.df1.plan import MapItem, plan_df1
from gateway.protocols.df1.framing import Checksum, encode_frame
from gateway.protocols.df1.pccc import ProtectedTypedLogicalRead, encode_command

EXHAUSTIVE_MAX = 14  # spans per file for the exhaustive search (2^13 cuts)

# file letter -> (file type code, file number, words per element)
FILES = {
    "N7": (0x89, 7, 1),
    "N10": (0x89, 10, 1),
    "B3": (0x85, 3, 1),
    "T4": (0x86, 4, 3),
    "C5": (0x87, 5, 3),
    "F8": (0x8A, 8, 2),
}


@functools.cache
def wire_bytes(file_type: int, file_number: int, element: int, sub_element: int, size: int) -> int:
    """Both directions of one read, ACKs included, from the encoders (reply data as zeros)."""
    request = ProtectedTypedLogicalRead(file_type, file_number, element, sub_element, size)
    command = encode_command(request, dst=1, src=0, tns=0x1234)
    # reply: DST SRC CMD|0x40 STS TNS(2) + data; built directly (not with the gateway's encode_reply)
    reply = bytes((0, 1, 0x4F, 0, 0x34, 0x12)) + bytes(size)
    return len(encode_frame(command, Checksum.CRC)) + 2 + 2 + len(encode_frame(reply, Checksum.CRC))


def block_bytes(key: str, start_word: int, words: int) -> int:
    file_type, file_number, element_words = FILES[key]
    element, sub = divmod(start_word, element_words)
    return wire_bytes(file_type, file_number, element, sub, 2 * words)


# --------------------------------------------------------------------------------------------
# random maps


def random_map(rng: random.Random) -> tuple[list[MapItem], dict[str, set[tuple[int, int]]]]:
    """Map items (for the planner) and the needed spans per file (computed here, independently)."""
    items: list[MapItem] = []
    needed: dict[str, set[tuple[int, int]]] = {}
    next_start = {"holding": 0, "input": 0, "coil": 0}
    dense = rng.random() < 0.5  # half the maps: many short N7 runs over N7:0-139
    for _ in range(rng.randint(8, 14) if dense else rng.randint(4, 10)):
        kind = "N7" if dense and rng.random() < 0.7 else rng.choice(["N7", "N7", "N10", "B3", "T4", "C5", "F8"])
        spans = needed.setdefault(kind, set())
        if kind in ("N7", "N10"):
            if dense:
                first, count = rng.randint(0, 135), rng.randint(1, 6)
            else:
                first, count = rng.randint(0, 70), rng.randint(1, 16)
            table_name = "holding"
            address = f"{kind}:{first}"
            spans.update((first + k, 1) for k in range(count))
            item = MapItem(table_name, next_start[table_name], address, count)
            size = count
        elif kind == "F8":
            first, count = rng.randint(0, 30), rng.randint(1, 5)
            table_name = "input"
            spans.update((2 * (first + k), 2) for k in range(count))
            item = MapItem(table_name, next_start[table_name], f"F8:{first}", count, "float32")
            size = 2 * count
        elif kind in ("T4", "C5"):
            first, count = rng.randint(0, 20), rng.randint(1, 4)
            table_name = "input"
            spans.update((3 * (first + k) + 2, 1) for k in range(count))
            item = MapItem(table_name, next_start[table_name], f"{kind}:{first}.ACC", count)
            size = count
        else:  # B3 bits as coils
            word, bit, count = rng.randint(0, 40), rng.randint(0, 15), rng.randint(1, 24)
            table_name = "coil"
            spans.update(((word * 16 + bit + k) // 16, 1) for k in range(count))
            item = MapItem(table_name, next_start[table_name], f"B3:{word}/{bit}", count, "bool")
            size = count
        items.append(item)
        next_start[table_name] += size + rng.randint(0, 5)
    return items, needed


# --------------------------------------------------------------------------------------------
# independent optima


def exhaustive(key: str, spans: set[tuple[int, int]], max_words: int, aligned: bool = True) -> int:
    """Cheapest cover of ``spans`` by trying every cut of the sorted spans into groups."""
    element_words = FILES[key][2] if aligned else 1
    ordered = sorted(spans)
    n = len(ordered)
    if n > EXHAUSTIVE_MAX:
        raise ValueError("too many spans for the exhaustive search")
    best = None
    for cuts in itertools.product((False, True), repeat=n - 1):
        total = 0
        first = 0
        for i in range(n):
            if i == n - 1 or cuts[i]:
                group = ordered[first : i + 1]
                start = group[0][0] - group[0][0] % element_words
                end = max(f + c for f, c in group)
                if end - start > max_words:
                    total = -1
                    break
                total += block_bytes(key, start, end - start)
                first = i + 1
        if total >= 0 and (best is None or total < best):
            best = total
    assert best is not None
    return best


def dp_over_words(key: str, spans: set[tuple[int, int]], max_words: int, aligned: bool = True) -> int:
    """Cheapest cover, any block [start, end) with start on an element boundary (or any word)."""
    element_words = FILES[key][2] if aligned else 1
    words = sorted({f + k for f, c in spans for k in range(c)})
    # a span must be read whole by one block
    span_of = {}
    for f, c in spans:
        for k in range(c):
            span_of[f + k] = (f, c)

    @functools.cache
    def best_from(index: int) -> int:
        if index == len(words):
            return 0
        first = span_of[words[index]][0]
        options = []
        lowest = max(0, first - max_words)
        for start in range(first - first % element_words, lowest - 1, -element_words):
            for end in range(first + 1, start + max_words + 1):
                # every span the block touches must end inside it
                j = index
                ok = True
                while j < len(words) and words[j] < end:
                    f, c = span_of[words[j]]
                    if f + c > end:
                        ok = False
                        break
                    j += 1
                if not ok:
                    continue
                if j < len(words) and words[j] < end:
                    continue
                options.append(block_bytes(key, start, end - start) + best_from(j))
            if start == 0:
                break
        return min(options)

    return best_from(0)


def planner_bytes(items: list[MapItem], max_read_bytes: int) -> int:
    plan = plan_df1(items, max_read_bytes)
    total = 0
    for block in plan.blocks:
        r = block.request
        total += wire_bytes(r.file_type, r.file_number, r.element, r.sub_element, r.size)  # type: ignore[attr-defined]
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few maps (CI smoke test)")
    parser.add_argument("--maps", type=int, default=0, help="random maps per read size limit (default 200; quick 10)")
    parser.add_argument("--seed", type=int, default=2024)
    args = parser.parse_args()
    maps = args.maps or (10 if args.quick else 200)
    print_machine()
    rows = []
    ratios_all: list[float] = []
    worst_seed = None
    worst = 0.0
    for max_read_bytes in (236, 82):  # SLC 5/03-5/05; SLC 500 fixed, 5/01, 5/02
        max_words = max_read_bytes // 2
        ratios, unaligned_gain, blocks, bytes_planned = [], [], [], []
        exact = files_exhaustive = files_total = 0
        for n in range(maps):
            seed = args.seed * 1000 + n
            items, needed = random_map(random.Random(seed))
            planned = planner_bytes(items, max_read_bytes)
            optimum = 0
            optimum_any_start = 0
            for key, spans in needed.items():
                exhaustive_cost = exhaustive(key, spans, max_words) if len(spans) <= EXHAUSTIVE_MAX else None
                files_exhaustive += exhaustive_cost is not None
                files_total += 1
                dp_cost = dp_over_words(key, spans, max_words)
                if exhaustive_cost is not None and exhaustive_cost != dp_cost:
                    raise SystemExit(f"seed {seed} {key}: exhaustive {exhaustive_cost} != DP {dp_cost}")
                optimum += dp_cost
                optimum_any_start += dp_over_words(key, spans, max_words, aligned=False)
            ratio = planned / optimum
            ratios.append(ratio)
            ratios_all.append(ratio)
            unaligned_gain.append(optimum / optimum_any_start)
            exact += planned == optimum
            blocks.append(len(plan_df1(items, max_read_bytes).blocks))
            bytes_planned.append(planned)
            if ratio > worst:
                worst, worst_seed = ratio, (seed, max_read_bytes)
        rows.append([max_read_bytes, maps, f"{files_exhaustive}/{files_total}", statistics.mean(blocks),
                     statistics.mean(bytes_planned),
                     statistics.mean(ratios), max(ratios), f"{exact}/{maps}", statistics.mean(unaligned_gain),
                     max(unaligned_gain)])
    print(table(["max read bytes", "maps", "files searched exhaustively", "blocks/scan", "planner bytes/scan",
                 "planner/optimum mean",
                 "planner/optimum worst", "planner = optimum", "optimum: element starts / any-word starts mean",
                 "worst"], rows))
    if worst_seed is not None and worst > 1.0:
        seed, limit = worst_seed
        items, _ = random_map(random.Random(seed))
        entries = ", ".join(f"{i.address} x{i.count}" for i in items)
        print(f"worst map (seed {seed}, max read {limit} bytes): {entries}")
        for block in plan_df1(items, limit).blocks:
            print(f"  planner block {block.label}")
    result(maps=2 * maps, mean_ratio=statistics.mean(ratios_all), worst_ratio=max(ratios_all),
           target_met=max(ratios_all) <= 1.05)


if __name__ == "__main__":
    main()
