"""MODELS/: a model's folder appears only whole, and summary.csv says what became of every entry.

A model is written into a hidden folder beside its place and renamed into it when every file
is there, so a run killed at any moment leaves either no MODELS/NAME/ or a whole one: a rerun
skips the whole ones (:meth:`Models.complete`) and fits the rest. fit writes absolute paths
(the params file's ``weights_in``, its header): the files come back naming the worker's scratch
folder and are given their place's path here (:func:`relocated`), the very bytes a serial
``lenn-ros fit -o MODELS/NAME`` writes, or the entry fails saying so.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

from lenn_ros.fleet_fit.task import REPORT_TEXT, Outcome, report_figures

SUMMARY = "summary.csv"
COLUMNS = ("name", "status", "reason", "rmse_free_run", "nmse_free_run_db", "rmse", "nmse_db", "samples",
           "seconds", "worker")  # fmt: skip
#: what ``fit -o`` writes, and the report text beside it: a folder holding all of them is a model
COMPLETE = ("params.yaml", "weights.npz", "fit.json", REPORT_TEXT)
#: files that name the folder they were written to
TEXTS = ("params.yaml", "fit.json", REPORT_TEXT)
PARTIAL = ".partial-"


class Models:
    """The models' folder: which entries are done, putting a model in place whole, the summary."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).expanduser().resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        for stale in self.root.glob(f".*{PARTIAL}*"):  # what a killed run was writing
            shutil.rmtree(stale, ignore_errors=True)

    def folder(self, name: str) -> Path:
        return self.root / name

    def complete(self, name: str) -> bool:
        """MODELS/NAME/ holds every file a model has (only a whole model is ever renamed there)."""
        return all((self.folder(name) / file).is_file() for file in COMPLETE)

    def skipped(self, name: str) -> Outcome:
        """A whole model left as it is, its figures read from its fit.json."""
        folder = self.folder(name)
        try:
            figures = report_figures(json.loads((folder / "fit.json").read_text()))
        except (OSError, ValueError, TypeError):
            figures = {}
        return Outcome(name, "skipped", f"complete in {folder} (--force fits it again)", figures=figures)

    def install(self, outcome: Outcome) -> Outcome:
        """Put a done entry's files in MODELS/NAME/ whole (replacing what was there); the outcome, failed if not."""
        final = self.folder(outcome.name)
        partial = self.root / f".{outcome.name}{PARTIAL}{os.getpid()}"
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir()
        try:
            for name, content in outcome.files.items():
                texts = name in TEXTS
                text = relocated(content, outcome.written_to, str(final), outcome.read_from) if texts else content
                (partial / name).write_bytes(text)
        except RelocationError as error:
            shutil.rmtree(partial, ignore_errors=True)
            return _failed(outcome, str(error))
        if final.exists():  # --force, or a folder that was not a whole model
            old = self.root / f".{outcome.name}{PARTIAL}old-{os.getpid()}"
            final.rename(old)
            partial.rename(final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            partial.rename(final)
        outcome.files = {}  # in place: the bytes need not stay in memory for the summary
        return outcome

    def write_summary(self, outcomes: Iterable[Outcome]) -> Path:
        """MODELS/summary.csv, one row per entry (written whole, then renamed: a reader never sees half)."""
        path, partial = self.root / SUMMARY, self.root / f".{SUMMARY}{PARTIAL}{os.getpid()}"
        with partial.open("w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(COLUMNS)
            for outcome in outcomes:
                writer.writerow(summary_row(outcome))
        partial.replace(path)
        return path


def summary_row(outcome: Outcome) -> list[str]:
    """One entry's row of summary.csv (:data:`COLUMNS`)."""
    seconds = f"{outcome.seconds:.2f}" if outcome.status == "done" or outcome.seconds else ""
    figures = [outcome.figures.get(key, "") for key in COLUMNS[3:8]]
    return [outcome.name, outcome.status, outcome.reason, *figures, seconds, outcome.worker]


class RelocationError(Exception):
    """A file still names the worker's scratch folder after its paths were given their place."""


def relocated(content: bytes, written_to: str, final: str, read_from: dict[str, str] | None = None) -> bytes:
    """``content`` with the folder fit wrote to replaced by ``final``, and each copy of a log it read (``read_from``,
    ``--send-logs``: in the same scratch folder) by the log's own path, as text and as JSON writes them."""
    moved = {**(read_from or {}), written_to: final}
    for there in sorted(moved, key=len, reverse=True):  # (longest first: no path is replaced inside another)
        here = moved[there]
        for old, new in {there: here, json.dumps(there)[1:-1]: json.dumps(here)[1:-1]}.items():
            content = content.replace(old.encode(), new.encode())
    if Path(written_to).parent.name.encode() in content:
        raise RelocationError(f"a file still names {written_to} after relocation (a path YAML or JSON rewrote)")
    return content


def _failed(outcome: Outcome, reason: str) -> Outcome:
    outcome.status, outcome.reason, outcome.files = "failed", reason, {}
    return outcome
