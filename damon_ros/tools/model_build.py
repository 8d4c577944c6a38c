"""``damon-ros collect``, ``train`` and ``build-graph``: the command lines that build a model.

Each command parses its options, calls one step of :mod:`damon_ros.learning` and prints a
one-line (or JSON) summary; the algorithms themselves live there, so they can be called and
tested without argparse. The three share how they are named, how they report bad input
(exit code 2 with the message on stderr, never a traceback) and the ``--quiet`` switch for
the progress bars.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
DATA_HELP = "directory written by damon-ros collect"


def _parser(command: str, description: str) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=f"damon-ros {command}", description=description)


def _parse(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Add ``--quiet`` (last, as every command lists it) and parse."""
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser.parse_args(argv)


def _attempt(command: str, work: Callable[[], T],
             errors: tuple[type[Exception], ...] = (ValueError,)) -> T | None:
    """``work()``, or None after printing ``damon-ros <command>: <error>`` to stderr."""
    try:
        return work()
    except errors as exc:
        print(f"damon-ros {command}: {exc}", file=sys.stderr)
        return None


def _done(out, *parts: str) -> int:
    """Print a command's one-line summary — its parts joined by "; ", then where the result
    went — and return the success exit code."""
    print("; ".join(parts) + f" -> {out}")
    return 0


# ---- collect --------------------------------------------------------------------------
def collect_main(argv: list[str] | None = None) -> int:
    """``damon-ros collect``: collect a labelled data set."""
    from damon_ros.learning.collect import ARM_REACH, HAND_LENGTH, collect

    parser = _parser("collect", "Collect DAMON training samples (q, obstacle point, collision) "
                                "labelled with exact mesh distances; chunked and resumable.")
    parser.add_argument("--n", type=int, default=1_000_000, help="number of samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--chunk-size", type=int, default=5000)
    parser.add_argument("--spacing", type=float, default=0.15, help="obstacle-node grid (m)")
    parser.add_argument("--radius", type=float, default=0.03, help="point obstacle radius (m)")
    parser.add_argument("--margin", type=float, default=0.05, help="λ for the 'near' flag (m)")
    parser.add_argument("--near-contact-share", type=float, default=0.5,
                        help="share of contact-seeking configurations")
    parser.add_argument("--reach", type=float, default=ARM_REACH + HAND_LENGTH,
                        help="node ball radius about the shoulder (m)")
    parser.add_argument("--floor", type=float, default=0.0, help="table plane height (m)")
    args = _parse(parser, argv)
    meta = _attempt("collect", lambda: collect(
        args.n, args.seed, args.out, workers=args.workers, chunk_size=args.chunk_size,
        spacing=args.spacing, radius=args.radius, margin=args.margin,
        near_contact_share=args.near_contact_share, reach=args.reach, floor=args.floor,
        progress=not args.quiet))
    if meta is None:
        return 2
    t, c = meta["timing"], meta["counts"]
    return _done(args.out, f"{meta['n_samples']} samples, {meta['n_nodes']} obstacle nodes, "
                 f"colliding {c['collision']} ({100 * meta['collision_ratio']:.1f} %), "
                 f"within margin {c['near']} ({100 * meta['near_ratio']:.1f} %)",
                 f"this run {t['samples_this_run']} samples in {t['wall_s_this_run']:.1f} s "
                 f"({t['samples_per_s_this_run']} /s)")


# ---- train ----------------------------------------------------------------------------
def train_main(argv: list[str] | None = None) -> int:
    """``damon-ros train``: train the VAE on a collected data set into a model directory."""
    from damon_ros.learning.vae_training import load_training_rows, save_trained, train_vae

    parser = _parser("train", "Train the DAMON VAE (11-300-200-75-2) on collected samples; "
                              "writes vae.safetensors, vae.json and meta.json into the model "
                              "directory.")
    parser.add_argument("--data", required=True, help=DATA_HELP)
    parser.add_argument("--out", required=True, help="model directory to write")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--beta", type=float, default=1e-3, help="KL weight β")
    parser.add_argument("--flag-weight", type=float, default=10.0,
                        help="weight of the collision-flag BCE in the reconstruction loss")
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--val-fraction", type=float, default=0.1)
    parser.add_argument("--max-rows", type=int, default=0, help="use at most this many rows")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch threads (default: all cores; 1 is faster on a busy machine)")
    args = _parse(parser, argv)

    def work():
        x, data_meta = load_training_rows(args.data, args.max_rows, args.seed)
        return data_meta, *train_vae(x, args.epochs, args.batch_size, args.beta, args.lr,
                                     args.seed, args.flag_weight, args.val_fraction,
                                     threads=args.threads or None, progress=not args.quiet)

    trained = _attempt("train", work)
    if trained is None:
        return 2
    data_meta, vae, metrics = trained
    out = Path(args.out)
    stale = save_trained(out, vae, metrics, args.data, data_meta)
    if stale:
        print(f"damon-ros train: {', '.join(stale)} in {out} belong to the previous VAE; "
              "run damon-ros build-graph again", file=sys.stderr)
    m = metrics
    return _done(out, f"trained on {m['train_rows']} rows, {m['seconds_per_epoch']:.1f} s/epoch",
                 f"held-out: joints RMSE {m['joint_rmse_rad']:.3f} rad, point RMSE "
                 f"{m['point_rmse_m']:.3f} m, flag accuracy {m['flag_accuracy']:.3f}, latent "
                 f"AUC kNN {m['latent_auc_knn']:.4f} / poly3 {m['latent_auc_poly3']:.4f}")


# ---- build-graph ----------------------------------------------------------------------
def build_graph_main(argv: list[str] | None = None) -> int:
    """``damon-ros build-graph``: the latent graph and the GMR into a trained model directory."""
    from damon_ros.learning.graph import GraphBuildConfig
    from damon_ros.learning.graph_builder import complete_model, load_inputs

    parser = _parser("build-graph", "Build the latent graph and fit the GMR.")
    parser.add_argument("--data", required=True, help=DATA_HELP)
    parser.add_argument("--model", required=True, help="model directory from damon-ros train")
    parser.add_argument("--n-vertices", type=int, default=GraphBuildConfig.n_vertices)
    parser.add_argument("--grid", type=int, default=GraphBuildConfig.grid_size)
    parser.add_argument("--k-latent", type=int, default=GraphBuildConfig.k_latent)
    parser.add_argument("--k-joint", type=int, default=GraphBuildConfig.k_joint)
    parser.add_argument("--gmm-components", type=int, default=8)
    parser.add_argument("--margin", type=float, default=0.02, help="λ of p(collision) (m)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    args = _parse(parser, argv)
    model = Path(args.model)
    inputs = _attempt("build-graph", lambda: load_inputs(args.data, model),
                      (ValueError, OSError, json.JSONDecodeError))
    if inputs is None:
        return 2
    config = GraphBuildConfig(n_vertices=args.n_vertices, grid_size=args.grid,
                              k_latent=args.k_latent, k_joint=args.k_joint, seed=args.seed)
    stats = complete_model(model, *inputs, config, args.gmm_components, args.margin,
                           args.workers, not args.quiet)
    print(json.dumps(stats, indent=1))
    return 0
