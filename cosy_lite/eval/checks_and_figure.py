"""The input checks and the recall figure of ``cosy-lite eval``, on a second core.

Neither needs the errors until the very end: the checks (~0.15 s on the demo's file), matplotlib's
import (~0.3 s) and the figure's axes (~0.1 s) run in a forked process while this one reads and
prepares the evaluation and computes the errors; the curves are drawn there once the scores are known. Where forking is not safe
(:func:`cosy_lite.eval.evaluator.fork_is_safe`: not Linux, torch loaded, threads running), the
same steps run in this process, in the same order.

The two processes talk over a pipe: ``("checks", problems)`` back once the checks are done, then
``(result, png)`` to it and ``("figure", None)`` back once the PNG is written; ``("error", text)``
back if a step raised.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
from pathlib import Path
from typing import Any, Callable

from cosy_lite.bop.validate import Problem


class ChecksAndFigure:
    """``checks() -> problems`` started at once (forked where safe); :meth:`problems` waits for
    them, :meth:`draw` draws the figure of a result, :meth:`close` ends the process.

    The figure: ``layout()`` returns its axes, drawn ahead (an object whose ``save(result, png)``
    adds the curves), or None when they cannot be laid out ahead; then ``plot(result, png)`` draws
    it whole. In this process (not forked) only ``plot`` is used."""

    def __init__(self, checks: Callable[[], list[Problem]], layout: Callable[[], Any],
                 plot: Callable[[Any, Path], None]):
        from cosy_lite.eval.evaluator import fork_is_safe

        self._plot = plot
        self._problems: list[Problem] | None = None
        self._proc = None
        if fork_is_safe():
            ctx = mp.get_context("fork")
            self._conn, child = ctx.Pipe()
            self._proc = ctx.Process(target=_serve, args=(child, self._conn, checks, layout, plot),
                                     name="checks and figure", daemon=True)
            self._proc.start()
            child.close()
        else:
            self._problems = checks()

    def problems(self) -> list[Problem]:
        """The problems the checks found (waits for them)."""
        if self._problems is None:
            self._problems = self._receive("checks")
        return self._problems

    def draw(self, result: Any, png: Path) -> None:
        """Draw the figure of ``result`` (an :class:`~cosy_lite.eval.evaluator.EvalResult`) to ``png``;
        return once it is written."""
        if self._proc is None:
            self._plot(result, png)
            return
        self._conn.send((dataclasses.replace(result, targets=[]), png))  # (the per-target errors are not drawn)
        self._receive("figure")

    def close(self) -> None:
        """End the process (at once if it still waits for a figure)."""
        if self._proc is not None:
            self._conn.close()  # its recv() ends: it exits
            self._proc.join(timeout=5)
            self._proc = None

    def _receive(self, kind: str) -> Any:
        try:
            got, value = self._conn.recv()
        except EOFError:
            assert self._proc is not None  # (only the forked process sends)
            self._proc.join(timeout=5)
            raise RuntimeError(f"the process of the input checks and the figure ended unexpectedly "
                               f"(exit code {self._proc.exitcode})") from None
        if got == "error":
            raise RuntimeError(f"{kind}: {value}")
        assert got == kind, (got, kind)
        return value


def _serve(conn, parent_end, checks: Callable[[], list[Problem]], layout: Callable[[], Any],
           plot: Callable[[Any, Path], None]) -> None:
    """The forked process: the checks, the figure's axes, then one figure if asked."""
    parent_end.close()  # (its copy from the fork: else this end never sees the parent close it)
    try:
        conn.send(("checks", checks()))
    except Exception as e:  # noqa: BLE001 - reported by the parent
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    try:
        figure = layout()
    except Exception:  # noqa: BLE001 - drawn whole at the end instead, where any error is reported
        figure = None
    try:
        result, png = conn.recv()
    except EOFError:  # no figure wanted (bad input, or the evaluation failed)
        return
    try:
        if figure is not None:
            figure.save(result, png)
        else:
            plot(result, png)
    except Exception as e:  # noqa: BLE001 - reported by the parent
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    conn.send(("figure", None))
