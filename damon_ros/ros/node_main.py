"""A node's life: ``--help`` before ROS starts, one-line errors, spin, clean shutdown."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from damon_ros.ros.environment import freeze_start_up_heap, keep_freed_memory, limit_threads
from damon_ros.ros.launch import exit_with_parent
from damon_ros.ros.parameters import Param, print_help


def run_single_threaded(
    node_factory: Callable[[], Node],
    args: Sequence[str] | None = None,
) -> int:
    """Spin a node on a single-threaded executor until SIGINT/SIGTERM, then shut down cleanly.

    Every damon_ros node runs so; their real work is in threads of their own (`FixedRateLoop`,
    `TopicReader`). Measured on a 2-core machine, the loop thread of a 1 kHz node misses its
    2 ms bound 5-10x more often beside a multi-threaded executor, whose Python dispatch
    competes for the GIL, and the planner's multi-threaded executor once ran no goal callback
    for minutes while its main thread spun.
    """
    return _spin(node_factory, args, SingleThreadedExecutor)


def _spin(
    node_factory: Callable[[], Node],
    args: Sequence[str] | None,
    make_executor: Callable[[], Executor],
) -> int:
    # SIGINT and SIGTERM are left to rclpy's own handlers (SignalHandlerOptions.ALL): they
    # wake the executor's wait and end spin() with ExternalShutdownException. A Python
    # handler (signal.signal) would only run once the main thread leaves that wait, which
    # an idle node never does: measured, such a node ignored SIGTERM.
    args = list(sys.argv if args is None else args)
    rclpy.init(args=args)
    node = None
    executor = make_executor()
    try:
        node = node_factory()
        freeze_start_up_heap()  # built: what lives now is no collector pause later
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # A signal that lands between two waits lets spin() build its next wait set on the
        # already shut-down context and raise RCLError instead: still a normal shutdown.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            shutdown_hook = getattr(node, "on_shutdown", None)
            if shutdown_hook is not None:
                shutdown_hook()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0


def node_main(name: str, description: str, parameters: Sequence[Param],
              node_factory: Callable[[], Node], args: Sequence[str] | None = None,
              extra_help: str = "", errors: tuple[type[BaseException], ...] = (),
              config_file: str | None = None) -> int:
    """A node's console entry point: ``--help`` before any ROS start-up, a one-line error
    (exit 2) on bad parameters or files, otherwise `run_single_threaded`.

    ``config_file`` names the node's shipped parameters file in the help (default
    ``config/<name>.yaml``)."""
    from rclpy.exceptions import ParameterException

    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "--help" in own or "-h" in own:
        print_help(name, description, parameters, config_file)
        if extra_help:
            print(f"\n{extra_help}")
        return 0
    limit_threads()
    keep_freed_memory()  # a refusal changes nothing but speed: nothing to report
    exit_with_parent()
    try:
        return run_single_threaded(node_factory, argv)
    except (ValueError, OSError, ParameterException, *errors) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
