"""``acinoset anipose [PROJECT_DIR]``: solve an Anipose project's trials where Anipose would."""

from __future__ import annotations

import argparse
import os
import sys
import time


def register(sub) -> None:
    p = sub.add_parser("anipose", description="Read an Anipose project (config.toml, sessions, pose-2d/*.h5, "
                       "calibration/calibration.toml) and write each trial's pose-3d/<trial>.csv in Anipose's "
                       "layout plus the full result as pose-3d/<trial>.h5. Options of ours go in an [acinoset] "
                       "table of config.toml: method, skeleton, body, sync, fps.")
    p.add_argument("project", nargs="?", default=".", metavar="PROJECT_DIR",
                   help="the folder holding config.toml (default: this one)")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="trials solved at once, each in its own process (default: the number of CPUs)")
    p.add_argument("--force", action="store_true", help="solve trials whose outputs are already up to date too")
    p.add_argument("--list", action="store_true", help="only list the trials found and what a run would do")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graph.anipose import load_project, run_project, up_to_date
    from graph.app.cli import UsageError

    if args.jobs is not None and args.jobs < 1:
        raise UsageError("--jobs must be at least 1")
    project = load_project(args.project)
    say = lambda text: print(f"anipose: {text}", file=sys.stderr, flush=True)  # noqa: E731
    if project.ignored:
        say("ignored (no equivalent here): " + "; ".join(project.ignored))
    for note in project.notes:
        say(note)
    opts = project.options
    say(f"{len(project.trials)} trials; method {opts.method}, skeleton {opts.skeleton}, likelihood threshold "
        f"{opts.likelihood_threshold:g}" + (f", bones {', '.join('-'.join(b) for b in opts.bone_lengths)}"
                                             if opts.bone_lengths else "")
        + (f", smoothing given for {len(opts.motion_scale)} groups" if isinstance(opts.motion_scale, dict) else ""))
    if args.list:
        for t in project.trials:
            state = "up to date" if up_to_date(t, project.inputs) and not args.force else "to solve"
            print(f"{t.label}\t{','.join(t.cameras)}\t{state}")
        return 0
    jobs = args.jobs or os.cpu_count() or 1
    t0 = time.perf_counter()

    def report(event) -> None:
        if event.stage in ("solved", "failed", "skipped"):
            say(f"{event.trial}: {event.stage}" + (f": {event.message}" if event.message else ""))
        elif event.stage == "started":
            say(f"{event.trial}: started")
        else:
            say(f"{event.trial}: {event.fraction * 100:3.0f}% {event.stage}")

    outcomes = run_project(project, jobs=jobs, force=args.force, report=report)
    counts = {s: sum(o.status == s for o in outcomes) for s in ("solved", "skipped", "failed")}
    print(f"{len(outcomes)} trials: {counts['solved']} solved, {counts['skipped']} up to date, "
          f"{counts['failed']} failed, {time.perf_counter() - t0:.1f} s")
    for o in outcomes:
        if o.status == "failed":
            print(f"failed: {o.trial.label}: {o.message}")
    return 1 if counts["failed"] else 0
