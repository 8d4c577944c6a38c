"""Where the package's shipped files are, and how they and the files we write are read and
fingerprinted.

A source checkout (tests, ``pip install -e``) keeps ``config/`` and ``models/`` beside the
package; a colcon install puts them in ``share/damon_ros``, which ament_index knows. Every
module that needs a shipped file asks here, so the two layouts are handled in one place.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import yaml

PACKAGE = "damon_ros"
SOURCE_ROOT = Path(__file__).resolve().parents[2]
"""The checkout that holds ``damon_ros/`` (meaningful for a source or editable install)."""


def _share_dir() -> Path:
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory(PACKAGE))


def shipped_dir(name: str) -> Path:
    """``<name>/`` of the source checkout, else of the installed package share directory."""
    source = SOURCE_ROOT / name
    if source.is_dir():
        return source
    try:
        return _share_dir() / name
    except (ImportError, LookupError, OSError, ValueError) as exc:  # not installed
        raise FileNotFoundError(
            f"{name}/ is neither at {source} nor in an installed {PACKAGE} share directory "
            f"({exc})") from exc


def config_dir() -> Path:
    """The shipped ``config/`` directory."""
    return shipped_dir("config")


def config_file(name: str) -> Path:
    """A shipped config file, with an error that says where it was looked for."""
    path = config_dir() / name
    if not path.is_file():
        raise FileNotFoundError(f"config file {name!r} is not at {path}")
    return path


def default_model_dir() -> Path:
    """``models/default``: the model the nodes and tools load unless told otherwise."""
    return shipped_dir("models") / "default"


def public_scenarios_dir() -> Path:
    """The public scenarios: ``$DAMON_SCENARIOS`` or ``../shared/scenarios`` beside the repo."""
    env = os.environ.get("DAMON_SCENARIOS")
    if env:
        return Path(env)
    return SOURCE_ROOT.parent / "shared" / "scenarios"


def sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file, read in 1 MiB blocks (model and dataset files are checked by it)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_versioned_json(path: str | os.PathLike, fmt: str, version: int,
                        error: type[Exception], *, missing: str, document: str,
                        versioned: str) -> dict:
    """A JSON object whose ``format`` is ``fmt`` and ``version`` is ``version`` (the model's
    ``meta.json``, a data set's ``dataset.json``), or ``error`` saying which check failed:
    ``missing`` is the whole message for an absent file, ``document`` names what the file
    should be ("not a <fmt> <document>") and ``versioned`` whose version it is."""
    path = Path(path)
    if not path.is_file():
        raise error(missing)
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise error(f"{path}: not a {fmt} {document}")
    if doc.get("version") != version:
        raise error(f"{path}: {versioned} version {doc.get('version')!r}, this package reads "
                    f"{version}")
    return doc


def read_yaml_section(path: str | os.PathLike, section: str) -> dict:
    """One top-level mapping of a YAML file, with errors that name the file and section."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read: {exc.strerror}") from exc
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: is not valid YAML: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get(section), dict):
        raise ValueError(f"{path}: needs a top-level mapping {section!r}")
    return data[section]
