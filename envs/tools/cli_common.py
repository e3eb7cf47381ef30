"""Helpers shared by the ``viotb`` commands: progress, output, errors, choices and output folders.

One place for each contract of DESIGN.md: ``--json`` is one strict JSON line (:mod:`.jsonout`), errors exit 2
with a message naming the culprit, a diverged estimator exits :data:`EXIT_DIVERGED`, progress goes to stderr
(a live bar on a terminal, a line every few seconds otherwise, nothing with ``--quiet``), ``--out`` is
checked before any work (:mod:`.outdir`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from viotb.envs.tools.jsonout import dumps_strict, strict_result
from viotb.envs.tools.outdir import OutDirError, check_out_dir

EXIT_ERROR = 2
"""Exit status of bad input (a bad option, file or value; the message names it)."""
EXIT_DIVERGED = 3
"""Exit status of ``viotb eval`` when the estimator diverged (results are still written and printed)."""
ESTIMATORS = ("msckf", "window", "imu-only", "ground-truth")
"""Estimator names (``viotb.vio.factory.ESTIMATOR_NAMES``, repeated here so that ``--help`` stays fast)."""
FRONTENDS = ("klt", "sim")
"""Front ends (``viotb.vio.factory.FRONTEND_NAMES``)."""
PROGRESS_LINE_EVERY_S = 5.0
"""Seconds between progress lines when stderr is not a terminal."""

ProgressFn = Callable[[float, float], None]
"""Progress callback ``(done, total)`` passed to long-running library functions."""


def err_console() -> Console:
    """The stderr console (resolved at each call, so that test runners can swap ``sys.stderr``)."""
    return Console(stderr=True)


def choice_option(default: str, flag: str, what: str, choices: Sequence[str], help_text: str = "") -> str:
    """An option whose allowed values ``--help`` lists (``[a|b|c]``) and whose error says ``unknown <what>``.

    Args:
        default: Default value (one of ``choices``).
        flag: The option's name (``--estimator``).
        what: What a value is called in messages (``estimator``).
        choices: The allowed values.
        help_text: Help after the list of choices.
    """
    allowed = tuple(choices)

    def parse(value: str) -> str:
        if value not in allowed:
            raise ValueError(f"unknown {what} {value!r}; allowed: {', '.join(allowed)}")
        return value

    listing = "|".join(allowed)
    return typer.Option(
        default, flag, parser=parse, metavar=f"[{listing}]", help=f"One of {', '.join(allowed)}. {help_text}"
    )


def estimator_option(default: str = "msckf") -> str:
    """The ``--estimator`` option, its allowed values listed by ``--help``."""
    return choice_option(default, "--estimator", "estimator", ESTIMATORS, "Estimator.")


def frontend_option(default: str = "klt", help_text: str = "Front end.") -> str:
    """The ``--frontend`` option: ``klt`` (OpenCV KLT on images) or ``sim`` (simulated features)."""
    return choice_option(default, "--frontend", "front end", FRONTENDS, help_text)


def seed_option() -> int:
    """The ``--seed`` option (an integer >= 0; a bad value is named as ``--seed``)."""
    return typer.Option(0, "--seed", min=0, help="Random seed (>= 0); same seed, same result.")


def seed_range(text: str) -> list[int]:
    """Seeds from ``"0-19"`` (inclusive range) or ``"0,3,5"`` (the benchmarks' ``--seeds``).

    Raises:
        ValueError: Text that is neither (naming it).
    """
    try:
        if "-" in text:
            lo, hi = text.split("-")
            return list(range(int(lo), int(hi) + 1))
        return [int(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(f"seeds must look like 0-19 or 0,3,5, got {text!r}") from None


def quiet_option() -> bool:
    """The ``--quiet`` option (no progress on stderr)."""
    return typer.Option(False, "--quiet", "-q", help="No progress output on stderr.")


def overwrite_option() -> bool:
    """The ``--overwrite`` option (replace a non-empty ``--out`` when the run completes)."""
    return typer.Option(
        False, "--overwrite", help="Replace a non-empty --out folder (swapped in when the run completes)."
    )


def fail(message: str, code: int = EXIT_ERROR) -> NoReturn:
    """Print a clear error on stderr and exit with ``code``."""
    err_console().print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)
    raise typer.Exit(code=code)


def check_out(out: Path, overwrite: bool) -> Path:
    """:func:`viotb.envs.tools.outdir.check_out_dir` with the error as a CLI failure (before any work)."""
    try:
        return check_out_dir(out, overwrite)
    except OutDirError as exc:
        fail(str(exc))


def check_seconds(seconds: float | None) -> None:
    """Refuse a non-positive or non-finite ``--seconds``."""
    if seconds is not None and not (0.0 < seconds < float("inf")):
        fail(f"--seconds must be positive and finite, got {seconds}")


def _line_progress(description: str, every_s: float, clock: Callable[[], float]) -> ProgressFn:
    """A callback that writes ``description: 42.0 % (12 s)`` to stderr at most every ``every_s`` seconds."""
    start = clock()
    last = [start - every_s]

    def update(done: float, total: float) -> None:
        now = clock()
        if now - last[0] < every_s:
            return
        last[0] = now
        frac = f"{100.0 * done / total:5.1f} %" if total > 0 else f"{done:g}"
        sys.stderr.write(f"{description}: {frac} ({now - start:.0f} s elapsed)\n")
        sys.stderr.flush()

    return update


@contextmanager
def progress(
    description: str,
    enabled: bool = True,
    every_s: float = PROGRESS_LINE_EVERY_S,
    clock: Callable[[], float] = time.monotonic,
) -> Iterator[ProgressFn]:
    """Progress on stderr, yielded as a ``(done, total)`` callback.

    A live bar when stderr is a terminal; otherwise (a log file, CI, a pipe) one line at most every
    ``every_s`` seconds; nothing when ``enabled`` is False (``--quiet``).
    """
    console = err_console()
    if not enabled:
        yield lambda done, total: None
        return
    if not console.is_terminal:
        yield _line_progress(description, every_s, clock)
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(description, total=1.0)

        def update(done: float, total: float) -> None:
            bar.update(task, completed=done, total=max(total, 1e-9))

        yield update


def emit(result: Mapping, as_json: bool, title: str, reasons: Mapping[str, str] | None = None) -> None:
    """Print a result as a table (human) or one strict JSON line (``--json``); notes go to the console too.

    Non-finite numbers become ``null`` with a line in ``notes`` (:func:`.jsonout.strict_result`).
    """
    if as_json:
        sys.stdout.write(dumps_strict(result, reasons) + "\n")
        return
    clean = strict_result(result, reasons)
    console = Console()
    console.print(f"[bold]{escape(title)}[/bold]")
    for key, value in clean.items():
        if key != "notes":
            console.print(f"  {key:<26} {escape(str(value))}")
    for note in clean.get("notes", []):
        console.print(f"  [yellow]note:[/yellow] {escape(note)}")


def write_json(path: Path, result: Mapping, reasons: Mapping[str, str] | None = None) -> None:
    """Write a result file (``metrics.json``) as strict JSON."""
    path.write_text(dumps_strict(result, reasons, indent=2) + "\n")
