"""``damon-ros``: one entry point whose subcommands run each part of the pipeline.

Subcommands are resolved lazily (module path + function name) so that ``--help`` and the
light commands start without importing torch, pinocchio or rclpy.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys

# name -> (module, function taking argv and returning an exit code, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": ("damon_ros.tools.demo", "main",
             "closed-loop demo: every node over real DDS, a goal, plots and a summary"),
    "clearance": (
        "damon_ros.tools.clearance", "main",
        "load scenarios and print the robot's exact clearance to each obstacle",
    ),
    "collect": ("damon_ros.tools.model_build", "collect_main",
                "collect labelled samples [q, obstacle point, flag] (module 1 data)"),
    "train": ("damon_ros.tools.model_build", "train_main",
              "train the VAE latent manifold on collected samples"),
    "build-graph": ("damon_ros.tools.model_build", "build_graph_main",
                    "build the two-layer latent graph and fit the GMR into a model directory"),
    "analyze": ("damon_ros.tools.analysis", "main",
                "GMR runtime model, graph-size sweep (N*) and the paper's plots"),
    "ablation": ("damon_ros.tools.ablation", "main",
                 "what the manifold contributes: latent kNN vs joint kNN vs both, same vertices"),
    "bench": ("damon_ros.tools.bench", "main",
              "closed-loop benchmark vs OMPL on scenarios and MotionBenchMaker problems"),
    "report": ("damon_ros.tools.report", "main",
               "write docs/BENCHMARKS.md from bench result files"),
    "soak": ("damon_ros.tools.soak", "main",
             "all nodes for N minutes: throughput, latency, memory, contacts, limits"),
    "scenarios": ("damon_ros.tools.scenarios", "main",
                  "generate fresh scenario files like the public families (held-out sets)"),
    "bench-tracker": ("damon_ros.tools.bench_tracker", "main",
                      "the tracker against ground truth: containment, volume excess, errors"),
    "bench-loops": ("damon_ros.tools.bench_loops", "main",
                    "CPU of the two 1 kHz nodes alone, per process and thread"),
    "bench-search": ("damon_ros.tools.bench_search", "main",
                     "graph search times: compiled A*, one lazy iteration, whole routes (ms)"),
    "bench-robot": (
        "damon_ros.tools.bench_robot", "main",
        "micro-benchmark of FK, IK and distance queries (median µs)",
    ),
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="damon-ros",
        description="DAMON latent-manifold motion planning for the Franka Panda.",
        epilog="Run 'damon-ros <command> --help' for the options of one command.",
    )
    parser.add_argument("command", choices=sorted(SUBCOMMANDS), metavar="command",
                        help="one of: " + ", ".join(sorted(SUBCOMMANDS)))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments of the command")
    return parser


def _usage_table() -> str:
    width = max(map(len, SUBCOMMANDS))
    rows = [f"  {name:<{width}}  {SUBCOMMANDS[name][2]}" for name in sorted(SUBCOMMANDS)]
    return "commands:\n" + "\n".join(rows)


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = _parser()
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        print("\n" + _usage_table())
        return 0
    ns = parser.parse_args(argv)
    # SIGTERM ends a command like Ctrl-C, through its `finally` blocks: demo and soak stop
    # their node processes there (killed outright, they left five nodes running)
    signal.signal(signal.SIGTERM, _interrupt)
    module_name, function, _ = SUBCOMMANDS[ns.command]
    run = getattr(importlib.import_module(module_name), function)
    try:
        return int(run(ns.args) or 0)
    except KeyboardInterrupt:
        print("damon-ros: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
