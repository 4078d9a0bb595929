"""The text report of ``lenn-ros fit``, and its plot: how each output's model was chosen, then its test figures.

The JSON (``--json``, fit.json: :meth:`~lenn_ros.fit.result.FitResult.as_dict`) holds every
figure; the text is what a reader needs of the same :class:`~lenn_ros.fit.result.FitResult`:
the first dozen candidates, notes where the test part or the record needs one, and how to
start the node from the files written. Apart from the procedure: it formats the result and
computes nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lenn_ros.fit.delay import delays_text
from lenn_ros.fit.numbering import split_line
from lenn_ros.fit.records import record_lines
from lenn_ros.fit.result import FitResult, OutputReport


def plot(path: str | Path, result: FitResult, name: str) -> Path:
    """Plant against the model on the test part (one-step and free run) over their errors, one pair of panels
    per output, each with its 95 % bands (one-step and free run). ``name``: the data's, for the title."""
    from lenn_ros.plotting import plot_channels, plot_identification

    free_bands, one_bands = ([_per_sample(part, kind) for part in result.per_output]
                             for kind in ("free_run", "one_step"))  # fmt: skip
    series = (result.y_test, result.y_hat_test)
    if result.alone:
        title = f"{name}: free-run RMSE {result.rmse_free_run:.4g} on the test part"
        return plot_identification(path, *series, title, result.y_free_test, free_bands[0], one_bands[0])
    title = f"{name}: model on the test part (free run from the measured outputs before it)"
    return plot_channels(path, result.outputs, *series, title, result.y_free_test, free_bands, one_bands)


def _per_sample(part: OutputReport, kind: str) -> Any:
    """One output's ``kind`` band (``one_step``, ``free_run``) at each test sample, or its one number (a result
    made without the per-sample half-widths)."""
    widths = getattr(part, f"{kind}_half_width_test", None)
    if widths is not None and len(widths) == part.samples:
        return widths
    return part.intervals.get(kind, {}).get("half_width")


def format_report(result: FitResult, dt: float | None = None) -> str:
    """The text report: how each output's model was chosen, then its test figures."""
    lines = [f"{result.data}: {split_line(result.test_from, result.train_samples, result.samples, result.numbers)}"]
    lines += record_lines(result.records)
    lines += [f"  note: {done['text']}" for done in result.left_out.values()]
    if result.free_run.get("test_record_of_its_own"):
        lines.append(f"  note: {result.free_run['test_record_of_its_own']}")
    if result.alone:
        return "\n".join(lines + _model_lines(result.only, "  ") + _test_lines(result, dt))
    for part in result.per_output:
        lines.append(f"  output {part.name}:")
        lines += _model_lines(part, "    ")
    lines += _table_lines(result)
    lines += _closing_lines(result, dt)
    return "\n".join(lines)


def _model_lines(part: OutputReport, indent: str) -> list[str]:
    """How one output's model was chosen and what it is."""
    m, c = part.model, part.choices
    scaling = c["scaling"]
    if "offsets" in scaling:
        shown = ", ".join(f"{n} = {o:.6g} +- {scaling['scales'][n]:.6g}" for n, o in scaling["offsets"].items())
    else:
        shown = (
            f"y = {scaling['y_offset']:.6g} +- {scaling['y_scale']:.6g}, "
            f"u = {scaling['u_offset']:.6g} +- {scaling['u_scale']:.6g}"
        )
    lines = [
        f"{indent}scaling from the training samples, margin {scaling['margin']:.0%}: {shown}",
        f"{indent}structure judged by the free runs of {c['blocks']} blocks of the training samples"
        + (f" ({c['gaps']} gaps in the record, not joined)" if c.get("gaps") else "")
        + ":",
    ]
    lines += _candidate_lines(c, indent)
    lines.append(f"{indent}time scale: {c['time_scale']}")
    if dead := c.get("dead_time"):
        lines.append(
            f"{indent}dead time: {delays_text(tuple(dead.values()), tuple(dead))} (the newest lags that add nothing "
            "to a least-squares model, up to a sharp onset): the terms read each input from there back"
        )
    if sign := c.get("sign"):
        blocks = sign["rmse_blocks"]
        lines.append(
            f"{indent}output read as |y|: fitted on its signed record too ({sign['runs']} runs between near-zero "
            f"minima; blocks' free-run RMSE {blocks['as_measured']:.5g} as read, {blocks['signed']:.5g} signed): "
            + ("the node signs each y_p as its model does (y_abs)" if sign["used"] else "kept as read")
        )
    if m["network"] == "lenn" and "epochs" in m:
        e = m["epochs"]
        lines.append(f"{indent}trained by SGD epochs: {e['epochs']} run, best {e['best_epoch']} ({e['stopped']})")
    if m["network"] == "mlp":
        e = m["epochs"]
        lines.append(f"{indent}model: MLP {m['structure']} hidden {m['expansion']['hidden']}, {m['n_terms']} weights")
        lines.append(f"{indent}trained by epochs: {e['epochs']} run, best {e['best_epoch']} ({e['stopped']})")
    else:
        terms = " + ".join(m["expansion"]["terms"])
        lines.append(f"{indent}model: {m['family']} ({m['expansion']['basis']}), {m['n_terms']} terms: {terms}")
    refinement = c["refinement"]
    if refinement.get("input_only"):
        lines.append(f"{indent}not refined: an input-only model's least squares already minimise its free-run error")
    elif refinement.get("done"):
        lines.append(
            f"{indent}refined on simulation error: {refinement['iterations']} of {refinement['tried']} iterations "
            f"(chosen on the blocks: held-out free-run RMSE {refinement['rmse_blocks_before']:.5g} -> "
            f"{refinement['rmse_blocks_after']:.5g})"
        )
        if refinement.get("unsound"):
            lines.append(f"{indent}  {refinement['unsound']} (the blocks vouch for the fit, not the stability)")
    live = m["live"]
    lines.append(
        f"{indent}live: RLS, forgetting {live['forgetting']:.6g}"
        if live["solver"] == "rls"
        else f"{indent}live: SGD, alpha {live['alpha']:.6g}, beta {live['beta']:.3g}"
    )
    return lines


def _table_lines(result: FitResult) -> list[str]:
    """Several outputs' test figures, one row each."""
    lines = [
        f"  test part ({result.samples} samples; free run of all outputs together from the "
        f"{result.free_run['starts_from']}):",
        "    output        one-step NMSE / RMSE      free-run NMSE / RMSE    95 % free-run band covers",
    ]
    for part in result.per_output:
        band = part.intervals["free_run"]
        lines.append(
            f"    {part.name:<12} {part.nmse_db:8.2f} dB {part.rmse:10.4g}   "
            f"{part.nmse_free_run_db:8.2f} dB {part.rmse_free_run:10.4g}   "
            f"+-{band['half_width']:.4g}: {band['coverage_test']:.1%}"
        )
    for part in result.per_output:
        notes = _beyond_lines(part, "  ") + _unlike_lines(part, "  ")
        lines += [line.replace("note: ", f"note ({part.name}): ", 1) for line in notes]
    return lines


#: candidates listed in the text report (the JSON has them all)
SHOWN_CANDIDATES = 12


def _candidate_lines(choices: dict[str, Any], indent: str = "  ") -> list[str]:
    lines = []
    listed = choices["candidates"]
    for index, candidate in enumerate(listed[:SHOWN_CANDIDATES]):
        mark = "->" if index == choices["chosen"] else "  "
        value = candidate["rmse_free_run_validation"]
        shown = f"free-run RMSE {value:.5g}" if value is not None else f"rejected: {candidate['rejected']}"
        if candidate.get("note"):
            shown += f" ({candidate['note']})"
        if candidate.get("refinement", {}).get("applied", True) is False:
            shown += f", the blocks chose {candidate['refinement']['iterations']} refinements (not applied: not chosen)"
        elif candidate.get("refinement"):
            shown += f", refined {candidate['refinement']['iterations']}x"
        lines.append(
            f"{indent} {mark} {candidate['family']} degree {candidate['degree']}, lags {candidate['y_lags']}/"
            f"{candidate['u_lags']}: {candidate['terms']} of {candidate['dictionary']} terms, {shown}"
        )
    if len(listed) > SHOWN_CANDIDATES:
        usable = sum(1 for c in listed if c["rmse_free_run_validation"] is not None)
        more = len(listed) - SHOWN_CANDIDATES
        lines.append(f"{indent}    ... {more} more ({usable} of {len(listed)} usable; --json lists all)")
    return lines


def _test_lines(result: FitResult, dt: float | None) -> list[str]:
    """One output's test figures, its bands and where the test part leaves the training range."""
    part = result.only
    lines = [f"  test part ({part.samples} samples):"]
    lines.append(f"    one-step: RMSE {part.rmse:.5g}, NMSE {part.nmse_db:.2f} dB")
    free = result.free_run
    lines.append(
        f"    free run (from the {free['starts_from']}): "
        f"RMSE {part.rmse_free_run:.5g}, NMSE {part.nmse_free_run_db:.2f} dB, "
        f"{free['clipped_inputs']} inputs clipped"
    )
    if part.intervals:
        lines.append(_band_line(part.intervals))
        lines += _blocks_line(part.intervals)
    outside = part.test_samples_outside_training_range
    if outside["u"] or outside["y"]:
        lines.append(
            f"  note: {outside['u']} test u and {outside['y']} test y samples lie beyond the training range "
            "plus margin; their network inputs are clipped (counted above)"
        )
    lines += _beyond_lines(part, "  ") + _unlike_lines(part, "  ")
    return lines + _closing_lines(result, dt)


def _band_line(bands: dict[str, Any]) -> str:
    """The 95 % bands in one line: each one's typical half-width, how it varies over the test part, its coverage."""
    one, run = bands["one_step"], bands["free_run"]
    spread = _spread(one, "wider the farther a regressor lies from the build data")
    growth = _spread(run, "growing with the steps since the run's start")
    source = "in-sample, optimistic" if "in-sample" in one["from"] else "from held-out blocks of the training samples"
    return (
        f"    95 % bands ({source}): one-step +-{one['half_width']:.4g}{spread} "
        f"covers {one['coverage_test']:.1%}, free run +-{run['half_width']:.4g}{growth} "
        f"covers {run['coverage_test']:.1%}"
    )


def _blocks_line(bands: dict[str, Any]) -> list[str]:
    """How much each band covered of held-out blocks it was not calibrated on: the spread a test part's coverage
    may show about 95 % (none where it was not measured)."""
    parts = [
        f"{label} {low:.1%}-{high:.1%}"
        for label, key in (("one step", "one_step"), ("free run", "free_run"))
        for low, high in [bands[key].get("held_out_blocks_covered") or (None, None)]
        if low is not None
    ]
    if not parts:
        return []
    return [
        f"    the same bands, each calibrated on the other blocks, covered of each held-out block: {', '.join(parts)} "
        "(a test part's coverage strays from 95 % about as far; further if it is unlike every block)"
    ]


def _spread(band: dict[str, Any], why: str) -> str:
    """' (+-low to +-high: why)' where a band's half-width varies over the test part ('' where it is one number)."""
    low, high = band.get("half_width_min_test"), band.get("half_width_max_test")
    if low is None or high is None or not high > low:
        return ""
    return f" (+-{low:.4g} to +-{high:.4g}: {why})"


def _unlike_lines(part: OutputReport, indent: str) -> list[str]:
    """One line when many test regressors lie farther from the build data than the build rows do."""
    said = part.intervals.get("unlike_build")
    return [f"{indent}note: {said}"] if said else []


def _beyond_lines(part: OutputReport, indent: str) -> list[str]:
    """One line when the test part leaves the training range: where, and what share of the error is there."""
    beyond = part.beyond_training_range
    if not beyond["samples"]:
        return []
    where = ", ".join(f"{name} {count}" for name, count in beyond["by_signal"].items())
    share = beyond["samples"] / part.samples
    return [
        f"{indent}note: {beyond['samples']} of {part.samples} test samples ({share:.0%}) lie beyond the range "
        f"of the training samples ({where}): the model extrapolates there; they carry "
        f"{beyond['free_run_error_share']:.0%} of the free run's squared error"
    ]


def _closing_lines(result: FitResult, dt: float | None) -> list[str]:
    """Warnings, the test part's length, the files written and how to start from them, the time taken."""
    lines = [f"  WARNING: {text}" for text in result.warnings]
    if dt:
        lines.append(f"  sample time {dt:g} s: test part {result.samples * dt:.4g} s")
    if result.files is not None:
        files = result.files
        lines.append(f"  wrote {files['params']}, {files['weights']} and {files.get('report', 'no report')}")
        lines.append(
            f"  live: ros2 run lenn_ros identifier --ros-args --params-file {files['params']} "
            "(its weights_in names the weights file)"
        )
        lines.append(f"  twin: ros2 run lenn_ros twin --ros-args -p model:={Path(files['params']).parent}")
    lines.append(f"  {result.seconds} s")
    return lines
