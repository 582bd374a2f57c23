"""An error quotes its offending input at most about 200 characters long, saying how long it
was: before, a 30 MB line of a bad g2o file was echoed whole into the error."""

from __future__ import annotations

from pathlib import Path

import pytest

from ssmvpr_common.quoting import QUOTE_LIMIT, quoted, shortened
from ssmvpr_common.trajectory_io import TrajectoryFileError, read_tum


def test_a_short_text_is_quoted_as_it_is() -> None:
    assert quoted("EDGE_SE2 0 1 x") == "'EDGE_SE2 0 1 x'"
    assert shortened("[1, 2]") == "[1, 2]"
    assert quoted("a" * QUOTE_LIMIT) == repr("a" * QUOTE_LIMIT)


def test_a_long_text_is_cut_with_an_ellipsis_and_its_length() -> None:
    text = "VERTEX_SE2 0 " + "9" * 3_000_000
    assert quoted(text) == repr(text[:QUOTE_LIMIT] + "…") + " (3,000,013 characters)"
    assert shortened(text) == text[:QUOTE_LIMIT] + "… (3,000,013 characters)"


def test_a_trajectory_file_with_a_huge_line_quotes_a_little_of_it(tmp_path: Path) -> None:
    path = tmp_path / "gt.tum"
    path.write_text("0 0 0 0 0 0 0 1\n" + "1 0 0 0 0 0 0 " + "x" * 5_000_000 + "\n")
    with pytest.raises(TrajectoryFileError) as caught:
        read_tum(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:2: not a number in '1 0 0 0 0 0 0 xxx")
    assert "(5,000,014 characters)" in message and len(message) < len(str(path)) + 300
