"""Progress bars are drawn on a terminal only, and never under `hidden_progress` (nested bars included)."""

from __future__ import annotations

import io
import sys

import pytest
from shapes import sphere

from geofeat.geometry import spectral
from geofeat.geometry.laplacian import laplacian
from geofeat.runtime.progress import hidden_progress, progress_bar


class Terminal(io.StringIO):
    """A text stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def drawn(show: bool = True, stream: io.StringIO | None = None) -> tuple[list[int], str]:
    stream = Terminal() if stream is None else stream
    items = list(progress_bar(range(4), desc="counting", show=show, file=stream, mininterval=0))
    return items, stream.getvalue()


def test_a_bar_is_drawn_on_a_terminal_only():
    items, text = drawn()
    assert items == [0, 1, 2, 3] and "counting" in text and "4/4" in text
    items, text = drawn(stream=io.StringIO())  # a file or a pipe: nothing written, the items still all there
    assert items == [0, 1, 2, 3] and text == ""
    items, text = drawn(show=False)
    assert items == [0, 1, 2, 3] and text == ""


def test_hidden_progress_hides_every_bar_until_the_outermost_block_ends():
    with hidden_progress():
        with hidden_progress():
            assert drawn()[1] == ""
        assert drawn()[1] == ""
    assert "counting" in drawn()[1]
    with pytest.raises(TypeError, match="show=False"):
        progress_bar(range(2), disable=True)


def test_the_nested_eigensolver_bar_follows_the_same_rule(monkeypatch):
    """The bar of a slow sparse eigen-solve (the nested bars seen under `geofeat demo`) goes through progress_bar."""
    lap = laplacian(sphere(3), "robust")  # 642 vertices: the sparse solver
    monkeypatch.setattr(spectral, "PROGRESS_AFTER_SECONDS", 0.0)  # draw it at once, whatever the machine's speed

    def solve_with_stderr(stream: io.StringIO) -> str:
        monkeypatch.setattr(sys, "stderr", stream)
        spectral.solve_eigenpairs(lap.stiffness, lap.mass, 20, name="sphere3", progress=True)
        return stream.getvalue()

    assert "eigenpairs of sphere3" in solve_with_stderr(Terminal())
    assert solve_with_stderr(io.StringIO()) == ""
    with hidden_progress():
        assert solve_with_stderr(Terminal()) == ""
