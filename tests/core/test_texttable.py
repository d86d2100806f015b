"""The one plain-text table layout (robustbench3d.texttable), checked against hand-written tables."""

from __future__ import annotations

import pytest

from robustbench3d.texttable import format_table


def test_columns_padded_to_the_widest_cell_with_a_rule():
    text = format_table(["name", "n"], [["ab", "12345"], ["abcdef", "7"]])
    assert text.split("\n") == [
        "name    n",
        "------  -----",
        "ab      12345",
        "abcdef  7",
    ]


def test_right_alignment_no_rule_and_no_trailing_spaces():
    text = format_table(["", "easy", "moderate"], [["Car BEV", "1.00", "100.00"], ["x", "", ""]], align="lrr",
                        rule=False)
    assert text.split("\n") == [
        "         easy  moderate",
        "Car BEV  1.00    100.00",
        "x",
    ]


def test_header_only_and_bad_shapes():
    assert format_table(["a", "bb"], []) == "a  bb\n-  --"
    with pytest.raises(ValueError, match="row 1 has 1 cells, the header 2"):
        format_table(["a", "b"], [["1", "2"], ["3"]])
    with pytest.raises(ValueError, match="align must be one of"):
        format_table(["a", "b"], [], align="lc")
