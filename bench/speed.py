"""How fast the learning rules and the identifier node are (run from a source checkout).

    python bench/speed.py                          # everything, 30 s online trials (~20 min)
    python bench/speed.py --quick --skip-online    # offline figures only, small sizes (~30 s)
    python bench/speed.py --json                   # one JSON object instead of markdown tables

The benchmarks live outside the installed package: they measure it, they are not part of it.
Offline (``bench/speed_offline.py``): cost per update of every example's
LeNN and MLP next to Table I's operation counts, training throughput against a
plain-numpy loop, ``Identifier.run`` and ``lenn-ros evaluate`` throughput, and the
compiled kernels checked against their pure-Python versions. Online
(``bench/speed_online.py``): the highest loss-free rate through ROS of a
do-nothing echo node and of the identifier, latency at 1 kHz, memory over a long
run, and where the identifier's time per message goes.

Figures are medians over repeated runs; ratios are formed within one run. The
benchmark prints what it measures next to the project's targets; it asserts nothing.
bench/RESULTS.md holds the latest tables (offline and online).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from typing import Any

import speed_offline as offline

TARGETS = {
    "lenn_offline": 1_000_000.0,  # samples/s, Ex. 1 LeNN training, one core
    "lenn_vs_numpy": 10.0,  # x the plain-numpy loop
    "mlp_offline": 100_000.0,  # samples/s, MLP {1-20-10-1}
    "online_fraction": 0.80,  # identifier rate / echo rate, both loss-free
    "p99_ms": 2.0,  # y_p(k) -> y_hat(k) at 1 kHz
}


def _log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def machine() -> dict[str, Any]:
    import numba
    import numpy

    return {
        "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "numba": numba.__version__,
        "compiled_kernels": offline.jit.COMPILED,
        "platform": platform.platform(),
    }


def run(
    quick: bool = False,
    online_seconds: float = 30.0,
    skip_online: bool = False,
    sizes: offline.Sizes | None = None,
) -> dict[str, Any]:
    """All measurements as one dict (see the module docstring); ``sizes`` overrides the preset."""
    started = time.perf_counter()
    sizes = sizes or (offline.QUICK if quick else offline.FULL)
    report: dict[str, Any] = {"quick": quick, "sizes": sizes.as_dict(), "machine_at_start": machine()}
    _log("offline: compiled vs py_func kernels")
    report["kernel_equality"] = offline.kernel_equality(sizes.equality_samples)
    _log("offline: cost per update, examples 1-4")
    report["cost_per_update"] = offline.cost_per_update(sizes)
    _log("offline: throughput")
    report["offline_throughput"] = offline.offline_throughput(sizes)
    clock = dict(offline.CLOCK)
    report["offline_clock"] = clock | {"cpu_share": clock["cpu_s"] / clock["wall_s"] if clock["wall_s"] else None}
    if skip_online:
        report["online"] = {"skipped": "--skip-online"}
    else:
        import speed_online as online

        seconds = min(online_seconds, 3.0) if quick else online_seconds
        report["online"] = online.online(seconds, quick, _log)
    report["targets"] = targets(report)
    report["machine_at_end"] = {"load_average": list(os.getloadavg())}
    report["seconds"] = time.perf_counter() - started
    return report


def targets(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Each target with the measured value and whether it is met (None: not measured)."""
    lenn = report["offline_throughput"]["lenn_ex1"]
    mlp = report["offline_throughput"]["mlp_ex1"]
    rows = [
        (
            "Ex. 1 LeNN offline training, one core",
            ">= 1 000 000 samples/s",
            lenn["samples_per_s"],
            TARGETS["lenn_offline"],
            ">=",
        ),
        ("Ex. 1 LeNN training vs plain-numpy loop", ">= 10x", lenn["speedup_vs_numpy"], TARGETS["lenn_vs_numpy"], ">="),
        (
            "MLP {1-20-10-1} offline training",
            ">= 100 000 samples/s",
            mlp["samples_per_s"],
            TARGETS["mlp_offline"],
            ">=",
        ),
    ]
    online = report.get("online", {})
    if "skipped" in online:
        rows += [
            ("identifier rate / echo rate, zero loss", ">= 80 %", None, TARGETS["online_fraction"], ">="),
            ("identifier latency p99 at 1 kHz", "< 2 ms", None, TARGETS["p99_ms"], "<"),
        ]
    else:
        p99 = online["identifier"].get("latency_at_1khz", {}).get("p99_ms")
        rows += [
            (
                "identifier rate / echo rate, zero loss",
                ">= 80 %",
                online.get("identifier_fraction_of_echo"),
                TARGETS["online_fraction"],
                ">=",
            ),
            ("identifier latency p99 at 1 kHz", "< 2 ms", p99, TARGETS["p99_ms"], "<"),
        ]
    result = []
    for name, goal, value, threshold, sense in rows:
        measured = value is not None and math.isfinite(value)
        met = None if not measured else (value >= threshold if sense == ">=" else value < threshold)
        result.append({"target": name, "goal": goal, "measured": value if measured else None, "met": met})
    return result


# --------------------------------------------------------------------------- markdown


def _num(value: Any, digits: int = 0) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, (int, float)) and digits == 0 and abs(value) >= 1000:
        return f"{value:,.0f}".replace(",", " ")
    return f"{value:.{digits}f}"


def _table(header: list[str], rows: list[list[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return lines


def markdown(report: dict[str, Any]) -> str:
    """The report as markdown: one section per part, then the targets."""
    out = _machine_markdown(report)
    out += _cost_markdown(report)
    out += _throughput_markdown(report)
    out += _equality_markdown(report)
    out += ["", "### 4. Online through ROS (subprocess node, private domain, localhost discovery)", ""]
    online = report["online"]
    out += [f"Skipped ({online['skipped']})."] if "skipped" in online else _online_markdown(online)
    out += _targets_markdown(report)
    return "\n".join(out)


def _machine_markdown(report: dict[str, Any]) -> list[str]:
    """Where and how the figures were measured."""
    sizes = report["sizes"]
    m = report["machine_at_start"]
    out = [
        f"Machine: {m['cpus']} CPUs (shared), load average {m['load_average'][0]:.2f} at start, "
        f"{report['machine_at_end']['load_average'][0]:.2f} at end; Python {m['python']}, numpy {m['numpy']}, "
        f"numba {m['numba']}; {'quick' if report['quick'] else 'full'} sizes, medians of {sizes['repeats']} runs; "
        f"total {report['seconds']:.0f} s."
    ]
    share = report["offline_clock"]["cpu_share"]
    out += [
        "",
        "Offline times are process CPU time (user + system), so other work on a shared core is not counted; "
        f"during them the benchmark got {_num(share * 100 if share else None, 0)} % of a core "
        "(CPU time / wall time; 100 % = an idle core).",
    ]
    return out


def _cost_markdown(report: dict[str, Any]) -> list[str]:
    """1. Cost per update, and the MLP / LeNN ratios next to Table I's."""
    out: list[str] = []
    sizes = report["sizes"]
    out += ["", "### 1. Cost per update (us per sample; Table I counts per training iteration)", ""]
    rows = []
    for row in report["cost_per_update"]:
        for kind in ("lenn", "mlp"):
            c = row[kind]
            rows.append(
                [
                    row["example"],
                    kind.upper() if kind == "mlp" else "LeNN",
                    c["weights"],
                    c["multiplications"],
                    c["tanh"],
                    _num(c["partial_fit_us"], 3),
                    _num(c["kernel_us"], 3),
                    _num(c["expansion_us"], 3) if kind == "lenn" else "-",
                    _num(c["predict_us"], 3),
                    _num(c["single_call_us"], 1),
                    _num(c["live_step_us"], 1),
                ]
            )
    out += _table(
        [
            "Ex.",
            "net",
            "weights",
            "Table I mult.",
            "tanh",
            f"partial_fit ({sizes['fit_samples']} samples)",
            "kernel only",
            "of which expansion",
            "predict",
            "1-sample update() call",
            "live Identifier.step",
        ],
        rows,
    )
    out += ["", "MLP / LeNN cost ratio, measured in the same run, vs Table I's multiplication ratio:", ""]
    out += _table(
        [
            "Ex.",
            "Table I mult.",
            "kernel only",
            "partial_fit",
            "predict",
            "1-sample call",
            "live step",
            "why they differ",
        ],
        [
            [
                row["example"],
                _num(row["table1_mult_ratio"], 1),
                _num(row["ratio_kernel"], 1),
                _num(row["ratio_partial_fit"], 1),
                _num(row["ratio_predict"], 1),
                _num(row["ratio_single_call"], 2),
                _num(row["ratio_live_step"], 2),
                offline.explain(row),  # from the row's figures (same text as row["explanation"] of this version)
            ]
            for row in report["cost_per_update"]
        ],
    )
    return out


def _throughput_markdown(report: dict[str, Any]) -> list[str]:
    """2. Offline throughput: compiled vs plain numpy, the MLP, Identifier.run, evaluate."""
    out: list[str] = []
    t = report["offline_throughput"]
    lenn, mlp, ident, bag = t["lenn_ex1"], t["mlp_ex1"], t["identifier_run_ex4"], t["evaluate_bag"]
    out += ["", "### 2. Offline throughput (samples/s, one core)", ""]
    rows = [
        [
            "Ex. 1 LeNN training, `partial_fit` (compiled, expansion included)",
            lenn["samples"],
            _num(lenn["samples_per_s"]),
        ],
        [
            "Ex. 1 LeNN learning rule alone (compiled kernel, features given)",
            lenn["samples"],
            _num(lenn["kernel_samples_per_s"]),
        ],
        [
            "Ex. 1 LeNN plain-numpy per-sample loop (same expansion, then the rule in numpy)",
            lenn["numpy_loop_samples"],
            _num(lenn["numpy_loop_samples_per_s"]),
        ],
        [
            "Ex. 1 plain-numpy rule alone (features given)",
            lenn["numpy_loop_samples"],
            _num(lenn["numpy_rule_only_samples_per_s"]),
        ],
        ["**speed-up, partial_fit vs numpy loop**", "", f"**{lenn['speedup_vs_numpy']:.1f}x**"],
        ["speed-up, compiled rule vs numpy rule (features given)", "", f"{lenn['kernel_speedup_vs_numpy_rule']:.1f}x"],
        ["Ex. 1 MLP {1-20-10-1} training, `partial_fit`", mlp["samples"], _num(mlp["samples_per_s"])],
        [
            "Ex. 4 LeNN through `Identifier.run` (regressors + expansion + guard)",
            ident["samples"],
            _num(ident["samples_per_s"]),
        ],
    ]
    if "skipped" in bag:
        rows.append(["`lenn-ros evaluate` on a bag", "-", f"skipped: {bag['skipped']}"])
    else:
        rows.append(
            [
                f"`lenn-ros evaluate BAG --json` (in-process; reading the bag is {bag['read_share']:.0%} of it)",
                bag["samples"],
                _num(bag["samples_per_s"]),
            ]
        )
    out += _table(["what", "samples", "samples/s"], rows)
    out.append("")
    out.append(
        f"The numpy loop and the compiled kernel implement the same rule: weights after "
        f"{lenn['numpy_loop_samples']} samples differ by at most {lenn['numpy_loop_max_abs_weight_difference']:.1e}."
    )
    return out


def _equality_markdown(report: dict[str, Any]) -> list[str]:
    """3. Compiled kernels against their pure-Python versions."""
    out: list[str] = []
    out += ["", "### 3. Compiled kernels vs their pure-Python `.py_func` (same inputs, same start state)", ""]
    out += _table(
        ["kernel", "samples", "max abs state difference", "max abs output difference", "py_func CPU time (s)"],
        [
            [
                name,
                e["samples"],
                f"{e['max_abs_state_difference']:.1e}",
                f"{e['max_abs_output_difference']:.1e}",
                _num(e["py_func_cpu_seconds"], 2),
            ]
            for name, e in report["kernel_equality"].items()
        ],
    )
    return out


def _targets_markdown(report: dict[str, Any]) -> list[str]:
    """The project's targets, measured value, met or not."""
    out: list[str] = []
    out += ["", "### Targets", ""]
    out += _table(
        ["target", "goal", "measured", "met"],
        [
            [
                r["target"],
                r["goal"],
                _target_value(r),
                "n/a" if r["met"] is None else ("yes" if r["met"] else "**no**"),
            ]
            for r in report["targets"]
        ],
    )
    return out


def _target_value(row: dict[str, Any]) -> str:
    value = row["measured"]
    if value is None:
        return "not measured"
    if "%" in row["goal"]:
        return f"{value:.0%}"
    if "x" in row["goal"]:
        return f"{value:.1f}x"
    if "ms" in row["goal"]:
        return f"{value:.2f} ms"
    return f"{_num(value)} samples/s"


def _online_markdown(online: dict[str, Any]) -> list[str]:
    """4. Rates, latency, all trials, memory, and where the identifier's time goes."""
    return [
        *_online_rates_markdown(online),
        *_online_summary_markdown(online),
        *_online_trials_markdown(online),
        *_online_memory_markdown(online),
        *_online_profile_markdown(online),
    ]


def _online_rates_markdown(online: dict[str, Any]) -> list[str]:
    """Highest loss-free rate and latency of the echo nodes and the identifier."""
    out = [
        f"Trials of {online['trial_seconds']:g} s after 200 warm-up samples; a trial passes when every sample is "
        "answered once, the identifier's status says lost = duplicates = 0 and paired = sent, the last reply comes "
        "within 0.25 s of its sample (no backlog), and the driver really published at the rate. "
        "CPU per sample is the node process's user + system time (all threads) over the trial, divided by the samples.",
        "",
    ]
    rows = []
    labels = {
        "echo": "echo node (`rclpy.spin`, no work)",
        "echo_waitset": "echo without executor (wait set, raw)",
        "identifier": "identifier (Ex. 1 LeNN, learning)",
    }

    def latency(entry: dict[str, Any] | None, verdict: bool = False) -> str:
        if not entry or "p50_ms" not in entry:
            return "n/a"
        text = f"{_num(entry['p50_ms'], 2)} / {_num(entry['p99_ms'], 2)}"
        return text + ("" if not verdict or entry.get("passed") else " (rate not sustained)")

    for name in ("echo", "echo_waitset", "identifier"):
        s = online[name]
        top = s.get("at_max_rate", {})
        limit = " (driver limit)" if s["driver_limited"] else ""
        rows.append(
            [
                labels[name],
                (_num(s["max_rate_hz"]) if s["max_rate_hz"] else "< 500") + limit,
                _num(s["first_failing_hz"]) if s["first_failing_hz"] else "-",
                _num(top.get("node_cpu_us_per_sample"), 0) if top else "n/a",
                latency(top),
                latency(s.get("latency_at_500hz"), True),
                latency(s.get("latency_at_1khz"), True),
            ]
        )
    out += _table(
        [
            "node",
            "highest loss-free rate (Hz)",
            "first failing (Hz)",
            "node CPU us/sample at that rate",
            "latency p50 / p99 (ms) at that rate",
            "at 500 Hz",
            "at 1 kHz",
        ],
        rows,
    )
    return out


def _online_summary_markdown(online: dict[str, Any]) -> list[str]:
    """Identifier / echo rate and where the identifier's extra CPU per sample goes."""
    profile = online["callback_profile"]
    fraction = online.get("identifier_fraction_of_echo")

    def cpu_at(name: str, rate: float) -> float | None:
        values = [t.get("node_cpu_us_per_sample") for t in online[name]["trials"] if t["rate_hz"] == rate]
        return values[0] if values and values[0] is not None and math.isfinite(values[0]) else None

    echo_cpu, identifier_cpu = cpu_at("echo", 500), cpu_at("identifier", 500)
    cpu_note = ""
    if echo_cpu and identifier_cpu:
        cpu_note = (
            f" At 500 Hz the identifier process spends {identifier_cpu:.0f} us of CPU per sample (all threads), "
            f"the echo {echo_cpu:.0f} us: {identifier_cpu - echo_cpu:.0f} us more, of which its callbacks' own "
            f"work is {profile['us_per_pair']:.0f} us; the rest is rclpy/DDS work the echo does not have (the executor "
            "rebuilds a bigger wait set for every message: more publishers and subscriptions, a timer; two more "
            "publications per pair). With transport as cheap as the echo's, the callbacks would allow "
            f"~{_num(online.get('predicted_identifier_max_hz'))} Hz."
        )
    return [
        "",
        f"Identifier / echo loss-free rate: **{_num(fraction * 100 if fraction is not None else None, 0)} %**. "
        f"The identifier's own work per pair (its callbacks called in-process, no transport) is "
        f"{profile['us_per_pair']:.0f} us of CPU, i.e. at most {_num(profile['max_rate_hz'])} pairs/s with free "
        f"transport.{cpu_note}",
        "",
        "All trials:",
        "",
    ]


def _online_trials_markdown(online: dict[str, Any]) -> list[str]:
    """Every online trial, passed or failed, with its problems."""
    rows = []
    for name in ("echo", "echo_waitset", "identifier"):
        for t in online[name]["trials"]:
            lat = t.get("latency", {})
            rows.append(
                [
                    name,
                    _num(t["rate_hz"]),
                    "pass" if t["passed"] else "fail",
                    _num(t.get("send_rate_hz")),
                    _num(t.get("reply_rate_hz")),
                    _num(t.get("end_lag_s"), 3),
                    _num(lat.get("p50_ms"), 2),
                    _num(lat.get("p99_ms"), 2),
                    _num(t.get("node_cpu_us_per_sample"), 0),
                    _num(t.get("driver_cpu_us_per_sample"), 0),
                    _num(t.get("load_average_1min"), 1),
                    "; ".join(t.get("problems", [])),
                ]
            )
    return _table(
        [
            "node",
            "rate",
            "",
            "sent/s",
            "replies/s",
            "last reply lag (s)",
            "p50 ms",
            "p99 ms",
            "node CPU us/sample",
            "driver CPU us/sample",
            "load",
            "problems",
        ],
        rows,
    )


def _online_memory_markdown(online: dict[str, Any]) -> list[str]:
    """The identifier's resident memory over a long run."""
    mem = online["memory"]
    out = ["", "Identifier memory over a long run (VmRSS from /proc every 0.5 s):", ""]
    out += _table(
        [
            "rate (Hz)",
            "seconds",
            "samples",
            "RSS start (kB)",
            "RSS end (kB)",
            "peak VmHWM (kB)",
            "growth (kB / 100k samples)",
            "trial",
        ],
        [
            [
                _num(mem["rate_hz"]),
                _num(mem["seconds"]),
                mem.get("samples", "n/a"),
                mem.get("rss_start_kb", "n/a"),
                mem.get("rss_end_kb", "n/a"),
                mem.get("rss_peak_kb", "n/a"),
                _num(mem.get("growth_kb_per_100k_samples"), 1),
                "pass" if mem["passed"] else "fail",
            ]
        ],
    )
    return out


def _online_profile_markdown(online: dict[str, Any]) -> list[str]:
    """cProfile of the callbacks in-process, and of the real identifier process."""
    profile = online["callback_profile"]
    out = [
        "",
        f"Where the identifier's own time per pair goes (cProfile of its callbacks over {profile['pairs']} pairs, "
        f"scaled to the unprofiled {profile['us_per_pair']:.0f} us of CPU per pair; indented rows are part of the "
        "row above):",
        "",
    ]
    out += _table(
        ["part", "us per pair", "share"],
        [
            [r["part"].replace("  ", "&nbsp;&nbsp;"), _num(r["us_per_pair"], 1), f"{r['share']:.0%}"]
            for r in profile["breakdown"]
        ],
    )
    out += ["", "Functions with the most own time (same profile):", ""]
    out += _table(
        ["function", "calls per pair", "own us per pair", "share"],
        [
            [f"`{r['function']}`", _num(r["calls_per_pair"], 1), _num(r["us_per_pair"], 1), f"{r['share']:.0%}"]
            for r in profile["top_own_time"]
        ],
    )
    process = online.get("process_profile", {})
    if "breakdown" in process:
        out += [
            "",
            f"The real identifier process under cProfile (main thread CPU time, {process['pairs']} pairs at "
            f"{_num(process['rate_hz'])} Hz; profiling makes it ~2x slower and inflates the executor's small Python "
            f"calls most, so its share is an upper estimate): {process['profiled_us_per_pair']:.0f} profiled us per "
            "pair, split:",
            "",
        ]
        out += _table(
            ["part", "share of the spinning thread's CPU"],
            [[r["part"].replace("  ", "&nbsp;&nbsp;"), f"{r['share']:.0%}"] for r in process["breakdown"]],
        )
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python bench/speed.py", description="speed: cost per update, offline and online throughput"
    )
    parser.add_argument("--quick", action="store_true", help="smaller sizes, for CI")
    parser.add_argument("--online-seconds", type=float, default=30.0, help="duration of each online rate trial")
    parser.add_argument("--skip-online", action="store_true", help="offline figures only")
    parser.add_argument("--json", action="store_true", help="one JSON object instead of markdown tables")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    report = run(quick=args.quick, online_seconds=args.online_seconds, skip_online=args.skip_online)
    if args.json:
        print(json.dumps(_finite_only(report), indent=1, allow_nan=False))
    else:
        print(markdown(report))
    return 0


def _finite_only(value: Any) -> Any:
    """JSON-ready copy: numpy scalars to Python, NaN / infinity to null (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): _finite_only(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_only(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


if __name__ == "__main__":
    sys.exit(main())
