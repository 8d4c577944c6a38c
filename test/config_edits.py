"""Copies of the shipped config files with one edit, for tests of how bad files are refused.

Every loader of a ``config/*.yaml`` section must name the field it refuses; the tests of
each (camera, tracker, ...) break one field of the shipped file and check the message.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import yaml

from damon_ros.core.resources import config_file


def edited_config(tmp_path: Path, name: str, section: str, edit: Callable[[dict], object]
                  ) -> Path:
    """The shipped ``config/<name>`` written to ``tmp_path`` after ``edit(data[section])``."""
    data = yaml.safe_load(config_file(name).read_text())
    edit(data[section])
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path
