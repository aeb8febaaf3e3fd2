"""Load test reports: a text table and a PNG (latency histogram + latency over time), matplotlib's Agg backend."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from .load import LoadRun, percentile


def _ms(value: float | None) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.0f}"


def format_table(summary: dict[str, Any]) -> str:
    """The summary of `clients.load.summarize` as an aligned two-column text table."""
    lat = summary["latency_ms"]
    if summary.get("mode") == "stream":
        mode = f"stream, {summary.get('devices')} device(s) at {summary.get('rate_hz')} frames/s each, in order"
    elif summary.get("mode") == "closed":
        mode = f"closed loop, concurrency {summary['concurrency']}"
    else:
        mode = f"open loop, {summary.get('rate_hz')} frames/s"
    rows: list[tuple[str, str]] = [
        ("target", str(summary.get("target", ""))),
        ("mode", mode),
        ("sent / ok", f"{summary['sent']} / {summary['ok']}"),
        ("errors", ", ".join(f"{k} {v}" for k, v in summary["errors"].items()) or "none"),
        ("retries", str(summary.get("retries", 0))),
        ("wall time", f"{summary.get('wall_s', 0.0):.1f} s"),
        ("throughput", f"{summary['throughput_fps']:.2f} frames/s"),
        ("latency p50 / p90 / p99 / max",
         f"{_ms(lat['p50'])} / {_ms(lat['p90'])} / {_ms(lat['p99'])} / {_ms(lat['max'])} ms"),
    ]
    if summary.get("mode") == "stream":
        warm = summary.get("warmup") or {}
        if warm.get("frames"):
            rows.append(("warm-up (apart)", f"{warm['answered']} of {warm['frames']} answered, max "
                         f"{_ms(warm.get('latency_ms_max'))} ms, {', '.join(warm.get('modes') or []) or '-'}"))
        rows.append(("answered / lost", f"{summary['answered']} / {summary['lost']}"))
        rows.append(("tracked / relocalized / global",
                     f"{summary['tracked']} / {summary['relocalized']} / {summary.get('global', 0)}"))
        worker = summary.get("tracked_worker_ms") or {}
        if worker.get("p50") is not None:
            stages = ", ".join(f"{k} {v:.1f}" for k, v in (worker.get("stage_ms_p50") or {}).items())
            rows.append(("tracked frame in the worker p50 / p90",
                         f"{worker['p50']:.1f} / {worker['p90']:.1f} ms ({stages})"))
    if summary.get("status_counts"):
        rows.append(("result status", ", ".join(f"{k} {v}" for k, v in summary["status_counts"].items())))
    acc = summary.get("accuracy")
    if acc is not None:
        med = acc.get("median_translation_m")
        rows.append(("success@5cm/5°", f"{100 * acc['success_5cm_5deg']:.1f} % of {acc.get('frames_scored', '?')}"))
        rows.append(("median translation error", "-" if med is None else f"{100 * med:.2f} cm"))
    else:
        rows.append(("accuracy", "n/a (no ground-truth poses)"))
    if summary.get("service_cpu_ms_per_request") is not None:
        rows.append(("service CPU per request", f"{summary['service_cpu_ms_per_request']:.0f} ms"))
    if summary.get("loadavg_1m"):
        rows.append(("machine load (1 min) start / end",
                     f"{summary['loadavg_1m']['start']:.1f} / {summary['loadavg_1m']['end']:.1f}"))
    rss = summary.get("service_rss_mb")
    if rss:
        rows.append(("service RSS start / 10% / end / max",
                     f"{rss['start']:.0f} / {rss.get('after_10pct', rss['start']):.0f} / {rss['end']:.0f} / "
                     f"{rss['max']:.0f} MiB"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def plot_run(run: LoadRun, path: str | Path) -> Path:
    """Write a PNG: latency histogram (left) and per-request latency over time, errors marked (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in run.records if r.code is None]
    bad = [r for r in run.records if r.code is not None and not math.isnan(r.done_s)]
    fig, (ax_h, ax_t) = plt.subplots(1, 2, figsize=(12, 4.5))
    lat = [r.latency_ms for r in ok]
    if lat:
        ax_h.hist(lat, bins=min(50, max(5, len(lat) // 5)), color="tab:blue")
        for q, style in ((50, "-"), (99, "--")):
            v = percentile(lat, q)  # as the table and the JSON give it
            ax_h.axvline(v, color="k", linestyle=style, linewidth=1, label=f"p{q} {v:.0f} ms")
        ax_h.legend()
    ax_h.set_xlabel("latency (ms)")
    ax_h.set_ylabel("requests")
    ax_h.set_title(f"{len(ok)} answered of {len(run.records)} sent")
    ax_t.scatter([r.scheduled_s for r in ok], lat, s=6, color="tab:blue", label="answered")
    if bad:
        ax_t.scatter([r.scheduled_s for r in bad], [(r.done_s - r.scheduled_s) * 1e3 for r in bad], s=14,
                     color="tab:red", marker="x", label="error")
    ax_t.set_xlabel("scheduled send time (s from start)")
    ax_t.set_ylabel("latency (ms)")
    ax_t.set_title(run.target)
    ax_t.legend(loc="upper left")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
