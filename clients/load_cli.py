"""`cadreg load`: replay a recorded-frames folder against a running service (plugin of the `cadreg` CLI).

    cadreg load (--url URL | --zenoh ENDPOINT) --site ID --frames FRAMES_DIR [--concurrency C | --rate R]
                [--n N | --duration S] [--range A:B[,C:D...]] [--json OUT.json] [--png OUT.png]
                [--stream [--device NAME] [--devices K]]

Prints a table (throughput, latency p50/p90/p99/max, errors by code, retries, accuracy against the folder's poses)
and writes the `--json` document of DESIGN §8. Exit status 0 when every request was answered, 1 otherwise.

--stream plays the frames IN ORDER as K devices, each its own tracking session (zenoh: stream mode on
cadreg/<site>/frames/<device>; HTTP: `session_id` = the device name), each at --rate frames/s (default 30), --n
frames per device (default: the frames once). The report adds answered, lost, tracked, relocalized and the worker's
time of tracked frames. --range picks frame numbers A <= i < B, ranges concatenated in order: `--range 0:100,400:500`
is a kidnapped robot.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any, Callable

from tqdm import tqdm

from cadreg.io.frames import RecordedFrames

from .frames import encode_recorded
from .load import (HttpTarget, LoadPlan, StreamPlan, ZenohTarget, process_tree_rss_mb, process_tree_stats,
                   rss_from_metrics, run_load, run_stream_http, run_stream_zenoh, select_indices, summarize)
from .report import format_table, plot_run
from .retry import RetryPolicy

log = logging.getLogger("cadreg.load")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "load",
        help="load-test a running service with a recorded-frames folder",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--url", help="HTTP base URL of the service, e.g. http://127.0.0.1:8080")
    where.add_argument("--zenoh", metavar="ENDPOINT", help="zenoh endpoint of the service, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--site", required=True, help="site id to localize in")
    p.add_argument("--frames", required=True, type=Path, help="recorded-frames folder (ScanNet export or 7-Scenes)")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--concurrency", type=int, help="closed loop: requests in flight (default 4)")
    how.add_argument("--rate", type=float, help="open loop: frames per second, latency from the scheduled time")
    p.add_argument("--n", type=int, help="requests to send (frames cycled; default: the folder's size)")
    p.add_argument("--duration", type=float, metavar="S", help="send for S seconds (with --n: whichever ends first)")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="per-request budget, retries included (default 60)")
    p.add_argument("--retries", type=int, default=None,
                   help="retries on 503 / connection errors (default: as many as fit in --timeout)")
    p.add_argument("--top-k", type=int, default=None, help="hypotheses to ask for (default: the service's)")
    p.add_argument("--raw-png", dest="raw", action="store_false",
                   help="re-encode every image as PNG instead of sending the folder's files as they are")
    p.add_argument("--server-pid", type=int, help="read the service's memory from /proc/PID (and its children)")
    p.add_argument("--json", type=Path, help="write the summary JSON here")
    p.add_argument("--records", type=Path, help="write one JSON line per request here")
    p.add_argument("--png", type=Path, help="write a latency histogram + latency-over-time PNG here")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--range", dest="frame_range", metavar="A:B[,C:D...]",
                   help="frame numbers A <= i < B to play, ranges concatenated in order (default: all)")
    p.add_argument("--stream", action="store_true",
                   help="play the frames in order as tracked device sessions (--rate per device, default 30)")
    p.add_argument("--device", default="load", help="--stream: device name (prefix of <NAME>-<k> with --devices)")
    p.add_argument("--devices", type=int, default=1, help="--stream: devices playing the frames at once (default 1)")
    p.add_argument("--warmup", type=int, default=1, metavar="W",
                   help="--stream: each device first sends W frames one at a time (its global localization), "
                        "reported apart; the timed stream follows (default 1; 0 = cold start)")
    p.add_argument("--lost-after", type=float, default=10.0, metavar="S",
                   help="--stream over zenoh: a frame with no pose this long after it was sent is lost (default 10)")
    p.set_defaults(func=run)


def _rss_sampler(args: argparse.Namespace, target: Any) -> Callable[[], float | None] | None:
    if args.server_pid is not None:
        return lambda: process_tree_rss_mb(args.server_pid)
    if args.url:
        import httpx  # the sampler runs beside the event loop's client: a small sync request is simplest

        def from_metrics() -> float | None:
            try:
                return rss_from_metrics(httpx.get(args.url.rstrip("/") + "/metrics", timeout=5.0).text)
            except httpx.HTTPError:
                return None

        return from_metrics if from_metrics() is not None else None
    return None


def _encode(args: argparse.Namespace, folder: RecordedFrames, limit: int | None) -> list:
    """The frames to send, encoded before the timed run: the --range selection (all by default), the first `limit`."""
    try:
        indices = select_indices(folder.indices, args.frame_range)
    except ValueError as exc:
        raise SystemExit(f"cadreg load: --range: {exc}") from None
    if not indices:
        raise SystemExit(f"cadreg load: no frame of {args.frames} in --range {args.frame_range}")
    indices = indices if limit is None else indices[:limit]
    with tqdm(total=len(indices), desc="encoding", unit="frame", disable=args.no_progress, file=sys.stderr) as bar:
        frames = []
        for i in indices:
            frames.append(encode_recorded(folder, i, top_k=args.top_k or 5, raw=args.raw))
            bar.update(1)
    kept = sum(len(f.raw_parts) for f in frames)
    log.info("encoded %d frames (%d parts sent as the files are, %.1f MB in all)", len(frames), kept,
             sum(f.nbytes for f in frames) / 1e6)
    return frames


def run(args: argparse.Namespace) -> int:
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one INFO line per request would drown the table
    folder = RecordedFrames.open(args.frames)
    if args.stream:
        if args.concurrency is not None or args.duration is not None:
            raise SystemExit("cadreg load: --stream plays frames at --rate per device; --concurrency and --duration "
                             "do not apply")
        try:
            plan: Any = StreamPlan(devices=args.devices, rate_hz=args.rate or 30.0, n=args.n, device=args.device,
                                   lost_after_s=args.lost_after, warmup=args.warmup)
        except ValueError as exc:
            raise SystemExit(f"cadreg load: {exc}") from None
        frames = _encode(args, folder, args.n)  # each device plays the first n (the sequence cycled past its end)
    else:
        if args.concurrency is None and args.rate is None:
            args.concurrency = 4
        n = args.n
        if n is None and args.duration is None:
            n = len(select_indices(folder.indices, args.frame_range)) if args.frame_range else len(folder)
        plan = LoadPlan(concurrency=args.concurrency, rate_hz=args.rate, n=n, duration_s=args.duration,
                        drain_timeout_s=args.timeout)
        frames = _encode(args, folder, n)
    before = process_tree_stats(args.server_pid) if args.server_pid is not None else None
    load_before = os.getloadavg()
    summary, run_ = asyncio.run(_drive(args, plan, frames))
    summary["loadavg_1m"] = {"start": load_before[0], "end": os.getloadavg()[0]}
    after = process_tree_stats(args.server_pid) if args.server_pid is not None else None
    if before is not None and after is not None and summary["sent"]:
        # CPU the service spent per request: tells a slow service from a starved one on a shared machine
        summary["service_cpu_ms_per_request"] = 1e3 * (after[1] - before[1]) / summary["sent"]
    print(format_table(summary))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
    if args.records:
        args.records.parent.mkdir(parents=True, exist_ok=True)
        from dataclasses import asdict

        args.records.write_text("".join(json.dumps(asdict(r)) + "\n" for r in run_.records))
    if args.png:
        plot_run(run_, args.png)
    return 0 if summary["ok"] == summary["sent"] else 1


async def _drive_stream(args: argparse.Namespace, plan: StreamPlan, frames: list, retry: RetryPolicy) -> tuple[dict, Any]:
    total = plan.devices * (plan.n if plan.n is not None else len(frames))
    counts = {"ok": 0, "err": 0}
    with tqdm(total=total, desc="stream", unit="frame", disable=args.no_progress, file=sys.stderr) as bar:
        def progress(rec: Any) -> None:
            counts["ok" if rec.code is None else "err"] += 1
            bar.update(1)
            bar.set_postfix(ok=counts["ok"], err=counts["err"], refresh=False)

        if args.url:
            result = await run_stream_http(args.url, args.site, frames, plan, timeout_s=args.timeout, retry=retry,
                                           progress=progress)
        else:
            # zenoh's publish/poll loop blocks: its device threads run beside the event loop
            result = await asyncio.to_thread(run_stream_zenoh, args.zenoh, args.site, frames, plan, progress=progress)
    return summarize(result), result


async def _drive(args: argparse.Namespace, plan: LoadPlan | StreamPlan, frames: list) -> tuple[dict, Any]:
    # by default the per-request budget (--timeout), not a count, ends the retries: an overloaded service then
    # costs latency, not frames, until the budget is spent
    retry = RetryPolicy(max_retries=args.retries if args.retries is not None else 1_000_000)
    if isinstance(plan, StreamPlan):
        return await _drive_stream(args, plan, frames, retry)
    target = (HttpTarget(args.url, args.site, timeout_s=args.timeout, retry=retry) if args.url
              else ZenohTarget(args.zenoh, args.site, timeout_s=args.timeout, retry=retry,
                               max_threads=max(64, plan.concurrency or 0)))
    total = plan.n if plan.duration_s is None else (
        int(plan.rate_hz * plan.duration_s) if plan.rate_hz else None)
    if total is not None and plan.n is not None:
        total = min(total, plan.n)
    counts = {"ok": 0, "err": 0}
    try:
        with tqdm(total=total, desc="load", unit="req", disable=args.no_progress, file=sys.stderr) as bar:
            def progress(rec: Any) -> None:
                counts["ok" if rec.code is None else "err"] += 1
                bar.update(1)
                bar.set_postfix(ok=counts["ok"], err=counts["err"], retries=target.retries, refresh=False)

            result = await run_load(target, frames, plan, progress=progress,
                                    rss_sampler=_rss_sampler(args, target))
    finally:
        await target.aclose()
    return summarize(result), result
