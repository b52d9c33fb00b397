"""The tests' cache of Hydra's config files (``helpers.hydra_cache``, on for the whole session)
reads a file again once it changed on disk, and keeps no file it could not read."""

from __future__ import annotations

import os

import pytest
import yaml
from hydra import compose, initialize_config_dir

from helpers import hydra_cache


def composed(folder, name="main"):
    with initialize_config_dir(str(folder), version_base="1.3"):
        return compose(config_name=name)


def test_a_config_file_changed_between_two_composes_is_read_afresh(tmp_path):
    (tmp_path / "main.yaml").write_text("defaults:\n  - part: a\n  - _self_\nvalue: 1\n")
    (tmp_path / "part").mkdir()
    part = tmp_path / "part" / "a.yaml"
    part.write_text("setting: 1\n")
    first = composed(tmp_path)
    assert (first.value, first.part.setting) == (1, 1)
    assert composed(tmp_path) == composed(tmp_path) == first  # kept: Hydra changes a copy
    assert any(key[0] == os.path.realpath(part) for key in hydra_cache._read)  # it was kept

    (tmp_path / "main.yaml").write_text("defaults:\n  - part: a\n  - _self_\nvalue: 22\n")
    assert composed(tmp_path).value == 22  # a new size
    before = os.stat(part)
    part.write_text("setting: 2\n")  # the same size: told apart by its mtime
    os.utime(part, ns=(before.st_atime_ns, before.st_mtime_ns + 1_000_000))
    assert composed(tmp_path).part.setting == 2


def test_a_file_that_does_not_parse_raises_and_is_read_again_once_fixed(tmp_path):
    (tmp_path / "main.yaml").write_text("value: [1, 2\n")
    with pytest.raises(yaml.YAMLError):
        composed(tmp_path)
    assert not any(key[0] == os.path.realpath(tmp_path / "main.yaml") for key in hydra_cache._read)
    (tmp_path / "main.yaml").write_text("value: [1, 2]\n")
    assert composed(tmp_path).value == [1, 2]
