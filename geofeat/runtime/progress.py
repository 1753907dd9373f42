"""Progress bars that stay quiet where nobody watches them.

Every progress bar geofeat draws goes through `progress_bar`: a `tqdm.auto` bar (a widget in
Jupyter) shown only when

- the caller asks for it (``show=True``, e.g. a function's ``progress`` argument),
- no `hidden_progress` block is active (``geofeat ... --no-progress`` hides every bar,
  the nested ones of the eigensolver included), and
- the stream it writes to (stderr) is a terminal.

Redirected to a file, a pipe or a CI log, a bar writes nothing, so logs hold no lines of
carriage-return updates.

>>> from geofeat.runtime.progress import hidden_progress, progress_bar
>>> for item in progress_bar(range(3), desc="items"):   # drawn on a terminal only
...     pass
>>> with hidden_progress():                             # drawn nowhere
...     total = sum(progress_bar(range(3)))
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from tqdm.auto import tqdm

__all__ = ["hidden_progress", "progress_bar"]

_hidden = 0


def progress_bar(iterable: Iterable | None = None, *, show: bool = True, **kwargs: Any) -> tqdm:
    """A tqdm bar, drawn only when ``show``, outside `hidden_progress` and on a terminal.

    Parameters
    ----------
    iterable : iterable, optional
        What to iterate over (as for ``tqdm``); None for a bar updated by hand (``total=``).
    show : bool
        False: never drawn.
    **kwargs
        Passed to ``tqdm`` (``total``, ``desc``, ``unit``, ``leave``, ``delay``, ``file``, ...);
        ``disable`` is set here and may not be given.

    Returns
    -------
    tqdm
        The bar; a hidden bar still iterates, counts and accepts ``update``/``set_postfix``.
    """
    if "disable" in kwargs:
        raise TypeError("progress_bar sets disable itself; pass show=False to hide the bar")
    # tqdm's disable=None: disabled when the output stream is not a terminal (Jupyter widgets show)
    return tqdm(iterable, disable=None if show and not _hidden else True, **kwargs)


@contextmanager
def hidden_progress() -> Iterator[None]:
    """Hide every progress bar made inside the block, nested ones included (blocks may nest)."""
    global _hidden
    _hidden += 1
    try:
        yield
    finally:
        _hidden -= 1
