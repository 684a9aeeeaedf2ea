"""Markdown tables: ``mean ± std`` cells and DataFrame.to_markdown's alignment."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from qtl.report.tables import markdown, markdown_table, seed_counts, stat_text
from tests.report.fakes import table_rows


def test_stat_text_rounds_and_one_seed_is_the_bare_value():
    assert stat_text(33.0, math.sqrt(18), 2) == "33.00 ± 4.24"
    assert stat_text(130.0, math.nan, 2) == "130.00"
    assert stat_text(3.0, math.nan, 1, whole=True) == "3"
    assert stat_text(1.5, math.sqrt(0.5), 1, whole=True) == "1.5 ± 0.7"


def test_markdown_keeps_text_cells_and_aligns_numbers_right():
    frame = pd.DataFrame({"Approach": ["PILCO", "QTL"], "m1.5": ["130.00", "7"], "Seeds": ["2", "1, 2"]})
    text = markdown(frame)
    assert table_rows(text) == [("Approach", "m1.5", "Seeds"), ("PILCO", "130.00", "2"), ("QTL", "7", "1, 2")]
    rule = text.splitlines()[1].strip("|").split("|")
    assert rule[0].startswith(":") and not rule[0].endswith(":")  # text left
    assert rule[1].endswith(":") and rule[2].endswith(":")  # numbers right


def test_seed_counts_collapse_when_equal():
    assert seed_counts([5, 5, 5]) == "5"
    assert seed_counts([5, 3]) == "5, 3"


def test_markdown_table_writes_each_cell_as_str_aligned_by_letter():
    text = markdown_table([["PILCO", 3, 0.5], ["QTL", None, "—"]], ["approach", "n", "x"], "lrl")
    assert table_rows(text) == [("approach", "n", "x"), ("PILCO", "3", "0.5"), ("QTL", "None", "—")]
    rule = text.splitlines()[1].strip("|").split("|")
    assert rule[0].startswith(":") and rule[1].endswith(":") and not rule[2].endswith(":")
    assert table_rows(markdown_table([["a", "b"]], ["x", "y"])) == [("x", "y"), ("a", "b")]  # default: l, then r


def test_markdown_refuses_an_alignment_that_does_not_fit_the_columns():
    frame = pd.DataFrame({"a": ["1"], "b": ["2"]})
    for align in ("l", "lx", "lrr"):
        with pytest.raises(ValueError, match="give one of l/r/c for each of 2 columns"):
            markdown(frame, align=align)
