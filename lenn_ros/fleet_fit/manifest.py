"""What a fleet fits: entries (a name, its records, fit's flags), from a YAML manifest or a folder of logs.

A manifest is checked whole before anything is submitted: a fleet of a thousand entries must
not fail at its 900th on a typo. Each refusal is one line naming the entry and the key. Every
entry's argv is also parsed by fit's own parser up front, so a flag fit does not know is
refused here, with fit's words, rather than on a worker.

    flags: [--u, input, --y, output, --test-from, "2401"]   # optional: every entry's, before its own
    entries:
      - name: arm1-elbow                                     # MODELS/arm1-elbow/
        records: [logs/arm1.csv]                             # or record: one path; relative to the manifest
        flags: "--network mlp"                               # a list, or one string split as a shell does
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shlex
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from lenn_ros.errors import UserError

#: fit's flags the fleet sets itself: where the model goes, and the report's form (text and fit.json both)
FLEET_OWNS = ("-o", "--output", "--json", "--plot")
#: what a folder of logs holds: CSV files, and bags (a directory with metadata.yaml or .mcap files, an .mcap file)
CSV_SUFFIXES = (".csv", ".txt", ".dat")
ENTRY_KEYS = {"name", "records", "record", "flags"}
TOP_KEYS = {"entries", "flags"}


class ManifestError(UserError):
    """A manifest or folder the fleet cannot fit from: one line naming the entry and the key."""


@dataclass(frozen=True)
class Entry:
    """One model to build: ``name`` (its folder under MODELS/), ``records`` (absolute paths), fit's ``flags``."""

    name: str
    records: tuple[str, ...]
    flags: tuple[str, ...]

    def argv(self, output: str) -> list[str]:
        """The argv of the serial ``lenn-ros fit`` of this entry, writing to ``output``."""
        return ["fit", *self.records, *self.flags, "-o", output]


def entries_from(
    source: str | Path, flags: list[str], fit_parser: Callable[[], argparse.ArgumentParser]
) -> list[Entry]:
    """The entries of a manifest (a YAML file) or of a folder of logs (one per log, with ``flags``), checked."""
    path = Path(source)
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        entries = folder_entries(path, flags)
    elif path.is_file() and path.suffix in (".yaml", ".yml"):
        entries = manifest_entries(path, flags)
    else:
        what = "one bag" if (path / "metadata.yaml").is_file() else "neither a manifest (.yaml) nor a folder"
        raise ManifestError(f"{source}: {what}: give a manifest (.yaml) or a folder of logs")
    check_entries(entries, fit_parser)
    return entries


def folder_entries(folder: Path, flags: list[str]) -> list[Entry]:
    """One entry per log in ``folder`` (CSV files, bag directories, .mcap files), named by the log."""
    logs = [p for p in sorted(folder.iterdir()) if _is_log(p)]
    if not logs:
        raise ManifestError(f"{folder}: no logs in it (CSV files {', '.join(CSV_SUFFIXES)}, bag directories, .mcap)")
    names = [p.stem if p.is_file() else p.name for p in logs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ManifestError(f"{folder}: two logs would make the model {twice[0]!r}: rename one, or use a manifest")
    return [Entry(name, (str(p.resolve()),), tuple(flags)) for name, p in zip(names, logs, strict=True)]


def _is_log(path: Path) -> bool:
    if path.name.startswith("."):
        return False
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(path.glob("*.mcap"))
    return path.suffix.lower() in (*CSV_SUFFIXES, ".mcap")


def manifest_entries(path: Path, flags: list[str]) -> list[Entry]:
    """The entries a YAML manifest names, each key checked (see the module's example)."""
    try:
        document = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ManifestError(f"{path}: not YAML: {' '.join(str(error).split())}") from None
    if not isinstance(document, dict) or not isinstance(document.get("entries"), list) or not document["entries"]:
        raise ManifestError(f"{path}: key 'entries': expected a list of entries (name, records, flags)")
    unknown = sorted(set(document) - TOP_KEYS)
    if unknown:
        raise ManifestError(f"{path}: unknown key {unknown[0]!r} (expected {', '.join(sorted(TOP_KEYS))})")
    common = [*flags, *_flags(document.get("flags", []), f"{path}: key 'flags'")]
    entries = [_entry(item, index, path.parent, common, path) for index, item in enumerate(document["entries"], 1)]
    names = [entry.name for entry in entries]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ManifestError(f"{path}: entry {twice[0]!r}: key 'name': given to two entries")
    return entries


def _entry(item: Any, index: int, base: Path, common: list[str], path: Path) -> Entry:
    where = f"{path}: entry {index}"
    if not isinstance(item, dict):
        raise ManifestError(f"{where}: expected a mapping with keys name, records, flags")
    name = item.get("name")
    if not isinstance(name, str) or not name.strip():
        raise ManifestError(f"{where}: key 'name': expected the model's folder name")
    where = f"{path}: entry {name!r}"
    if "/" in name or "\\" in name or name.startswith(".") or name != name.strip():
        raise ManifestError(f"{where}: key 'name': a folder name without '/', not starting with '.'")
    unknown = sorted(set(item) - ENTRY_KEYS)
    if unknown:
        raise ManifestError(f"{where}: unknown key {unknown[0]!r} (expected name, records, flags)")
    if ("records" in item) == ("record" in item):
        raise ManifestError(f"{where}: key 'records': give records (a list) or record (one path), one of them")
    key = "records" if "records" in item else "record"
    given = item[key] if isinstance(item[key], list) else [item[key]]
    if not given or not all(isinstance(r, str) and r for r in given):
        raise ManifestError(f"{where}: key {key!r}: expected paths of logs")
    records = []
    for record in given:
        full = (base / record).expanduser().resolve()
        if not full.exists():
            raise ManifestError(f"{where}: key {key!r}: {record} does not exist (relative paths: from {base})")
        records.append(str(full))
    own = _flags(item.get("flags", []), f"{where}: key 'flags'")
    return Entry(name, tuple(records), (*common, *own))


def _flags(value: Any, where: str) -> list[str]:
    if isinstance(value, str):
        return shlex.split(value)
    if isinstance(value, list) and all(isinstance(v, str | int | float) and not isinstance(v, bool) for v in value):
        return [str(v) for v in value]
    raise ManifestError(f"{where}: expected fit's flags, a list of strings or one string")


def check_entries(entries: list[Entry], fit_parser: Callable[[], argparse.ArgumentParser]) -> None:
    """Refuse flags the fleet sets itself, and any argv fit's own parser refuses (in fit's words)."""
    parser = fit_parser()
    for entry in entries:
        owned = [flag for flag in entry.flags if flag.split("=")[0] in FLEET_OWNS]
        if owned:
            raise ManifestError(f"entry {entry.name!r}: key 'flags': {owned[0]} is the fleet's (it writes MODELS/NAME)")
        said = io.StringIO()
        try:
            with contextlib.redirect_stderr(said):
                parser.parse_args(entry.argv("MODELS"))
        except SystemExit:
            reason = (said.getvalue().strip().splitlines() or ["fit refused it"])[-1].split("error: ", 1)[-1]
            key = "records" if any(record in reason for record in entry.records) else "flags"
            raise ManifestError(f"entry {entry.name!r}: key {key!r}: {reason}") from None
