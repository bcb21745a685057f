"""The summary's layout: one table formatter (service.text_table), so a long name or a large count never runs into the
text beside it (``follower[0] ×383,349 (x, u, w) triples`` read as ×3 and 83,349)."""

from __future__ import annotations

import re
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from service.cli import SUMMARY_WIDTH, summary_lines
from service.text_table import format_table


def _report(name: str, members: int, triples: int) -> dict:
    return {
        "name": "platoon", "abstract_states": 10**40, "subsystem_count": members + 1,
        "subsystems": [
            {"name": "leader", "triples": 12, "members": ["leader"]},
            {"name": f"{name}[0]", "triples": triples, "members": [f"{name}[{k}]" for k in range(members)],
             "growth_bound": "scp", "mean_successors": {"scp": 2.5}, "non_blocking": {"scp": triples},
             "blocking_fraction": 0.25},
        ],
        "domain_states": 123_456_789_012, "audit": {"transitions_checked": 1_000_000, "violations": 0},
        "stage_seconds": {"subsystems": 1.5},
    }


def test_a_label_of_fourteen_characters_keeps_a_gap_before_its_count():
    lines = summary_lines(_report("follower", 3, 83_349), Path("out"))
    row = next(line for line in lines if "follower[0]" in line)
    assert re.search(r"follower\[0\] ×3 {2,}83,349 \(x, u, w\) triples", row), row


def test_long_names_and_large_counts_stay_in_their_columns():
    name = "a_subsystem_with_a_rather_long_name_of_forty"
    lines = summary_lines(_report(name, 383_349, 12_345_678_901), Path("out"))
    assert all(len(line) <= SUMMARY_WIDTH for line in lines), lines
    row = lines.index(f"  {name}[0] ×383,349")  # wider than the label column: a line of its own
    column = 2 + 12 + 2  # the other labels are short
    assert lines[row + 1].startswith(" " * column + "12,345,678,901 (x, u, w) triples,")
    # Every other row's text starts in that column.
    leader = next(line for line in lines if line.startswith("  leader"))
    assert leader[column - 2:column + 2] == "  12", leader
    audit = next(line for line in lines if line.startswith("  audit"))
    assert audit[column:].startswith("1,000,000 transitions, 0 violations"), audit


def test_a_label_wider_than_the_column_gets_its_own_line():
    lines = format_table([("short", ["a"]), ("x" * 50, ["1,234,567 things", "more"])], width=60, max_label=20)
    assert lines[0] == "  short" + " " * 9 + "a"  # the column: 12 at least, as wide as the labels that fit
    assert lines[1] == "  " + "x" * 50
    assert lines[2] == " " * 16 + "1,234,567 things, more"


@given(st.lists(st.tuples(st.text("abc[]× ", min_size=1, max_size=30).map(str.strip).filter(bool),
                          st.lists(st.integers(0, 10**15).map(lambda n: f"{n:,} things"), min_size=1, max_size=6)),
                min_size=1, max_size=6))
def test_labels_and_text_never_touch(rows):
    lines = format_table(rows, width=80)
    column = max(12, max(len(label) for label, _ in rows if len(label) <= 40)) + 2 + 2
    texts = []
    for line in lines:
        assert len(line) <= 80 or " " not in line[column:].replace(", ", ""), line
        texts.append(line[column:])
        assert line[column - 1] == " " or len(line) <= column - 2  # the gap, or a label line of its own
    for _, parts in rows:  # the parts come back whole, a number next to its unit
        assert all(any(part in t for t in texts) for part in parts)
