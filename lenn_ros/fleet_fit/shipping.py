"""``--send-logs``: an entry's logs travel to the worker with its task, for workers that do not share the client's disk.

Without it the workers read the logs at the paths the manifest gives (a shared file system). With
it the client reads each entry's records as it submits the entry (:func:`pack`: a CSV or .mcap
file, or a bag directory's files), the worker writes them into its scratch folder under their own
names (:func:`unpack`) and fits them there; the files fit writes name the worker's copies, and the
client gives them the records' own paths again (:meth:`~lenn_ros.fleet_fit.store.Models.install`),
so the model is the very bytes a serial ``lenn-ros fit`` of the records writes. The client holds
the logs of the entries in flight only (:data:`IN_FLIGHT_PER_WORKER` per worker), not the fleet's.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from lenn_ros.errors import UserError
from lenn_ros.fleet_fit.manifest import Entry

#: entries submitted ahead per worker when their logs travel with them (each held in the client's memory till done)
IN_FLIGHT_PER_WORKER = 2
#: a record's files larger than this in all are refused (sent through the scheduler, they would stall it)
LARGEST_RECORD = 2 * 1024**3


class ShippingError(UserError):
    """A record that cannot be sent: one line naming the entry and the record."""


def sent_paths(entry: Entry) -> list[str]:
    """What a worker must read for the entry: its records, then the files its ``--test`` flags name (as given)."""
    tests = [f for flag, f in zip(entry.flags, entry.flags[1:], strict=False) if flag == "--test"]
    tests += [flag.split("=", 1)[1] for flag in entry.flags if flag.startswith("--test=")]
    return [*entry.records, *tests]


def pack(entry: Entry) -> dict[str, bytes]:
    """The entry's logs (:func:`sent_paths`) as files to send: ``"<i>/<name>"`` for log i's file, ``"<i>/<dir>/<path>"``
    for each file of a bag directory (its layout kept: metadata.yaml names its storage files relative to it)."""
    files: dict[str, bytes] = {}
    for i, log in enumerate(sent_paths(entry)):
        path = Path(log).expanduser().resolve()
        members = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        size = sum(p.stat().st_size for p in members)
        if size > LARGEST_RECORD:
            raise ShippingError(
                f"entry {entry.name!r}: {log}: {size / 1024**3:.1f} GiB is too large to send with --send-logs "
                "(put the logs where the workers read them, and leave the flag out)"
            )
        for member in members:
            files[f"{i}/{member.relative_to(path.parent).as_posix()}"] = member.read_bytes()
    return files


def unpack(entry: Entry, files: dict[str, bytes], folder: Path) -> tuple[Entry, dict[str, str]]:
    """Write :func:`pack`'s files under ``folder``: the entry reading those copies, and each copy's path -> the path
    the entry gave (which fit's files must name, as a serial fit of the entry writes them)."""
    for key, content in files.items():
        target = folder.joinpath(*key.split("/"))
        if not target.resolve().is_relative_to(folder.resolve()):  # (a key is the client's, but never trusted)
            raise ShippingError(f"entry {entry.name!r}: a sent file {key!r} would land outside the scratch folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(content)
    given = sent_paths(entry)
    names = {int(key.split("/")[0]): key.split("/")[1] for key in files}  # (as the client named each log: pack)
    copies = [str(folder / str(i) / names[i]) for i in range(len(given))]
    there = dict(zip(given, copies, strict=True))
    records = tuple(there[record] for record in entry.records)
    flags = [
        there.get(flag, flag) if before == "--test" else flag
        for before, flag in zip(("", *entry.flags), entry.flags, strict=False)
    ]
    flags = [f"--test={there[flag[7:]]}" if flag.startswith("--test=") else flag for flag in flags]
    return dataclasses.replace(entry, records=records, flags=tuple(flags)), dict(zip(copies, given, strict=True))
