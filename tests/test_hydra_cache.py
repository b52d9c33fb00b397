"""The tests' cache of Hydra's config files and builds (``helpers.hydra_cache``, on for the
whole session) reads a file again once it changed on disk, keeps no file it could not read, and
composes exactly what Hydra composes with its own reads."""

from __future__ import annotations

import os

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from helpers import hydra_cache
from lbo.core.paths import CONF_DIR


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


def hydras_own(name, overrides):
    """What Hydra composes with its own reads, the hydra node included."""
    hydra_cache.uninstall()
    try:
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            return compose(config_name=name, overrides=overrides, return_hydra_config=True)
    finally:
        hydra_cache.install()


def kept(name, overrides):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose(config_name=name, overrides=overrides, return_hydra_config=True)


def plain(cfg):
    """A composed config as plain data, less what differs between two composes anyway."""
    out = OmegaConf.to_container(cfg, resolve=False)
    out["hydra"]["runtime"].pop("output_dir", None)
    return out


@pytest.mark.parametrize("lines", [
    ["experiment=smoke", "seed=3", "data.root=/tmp/a", "+trainer.limit_val_batches=2"],
    ["experiment=smoke", "seed=4", "~callbacks.evaluation", "model.window=40"],
    ["model=lstm", "experiment=robust", "data=smoke", "optimizer.lr=0.5",
     "hydra.sweep.dir=/tmp/s"],
])
def test_a_kept_build_composes_what_hydra_composes(lines):
    """The same choices with other values, composed one after the other through the kept
    build, give exactly Hydra's own configs (the hydra node included: the overrides, choices
    and job name), and no value set by one line stays in the next."""
    for _ in range(3):  # the build, the kept merge, a copy of it
        assert plain(kept("train", lines)) == plain(hydras_own("train", lines))
    assert plain(kept("train", lines[:1])) == plain(hydras_own("train", lines[:1]))


def test_a_value_and_a_choice_of_the_same_line_are_told_apart(tmp_path):
    """``part=b`` chooses an option (another build), ``value=3`` sets a value (the kept
    build); a key that names a group only once the folder exists is a choice from then on."""
    (tmp_path / "main.yaml").write_text("defaults:\n  - part: a\n  - _self_\nvalue: 1\n"
                                        "other: {x: 1}\n")
    (tmp_path / "part").mkdir()
    (tmp_path / "part" / "a.yaml").write_text("setting: 1\n")
    (tmp_path / "part" / "b.yaml").write_text("setting: 2\n")

    def with_lines(*lines):
        with initialize_config_dir(str(tmp_path), version_base="1.3"):
            return compose(config_name="main", overrides=list(lines))

    assert (with_lines("value=3").value, with_lines("value=3").part.setting) == (3, 1)
    assert with_lines("part=b", "value=4") == {"part": {"setting": 2}, "value": 4,
                                               "other": {"x": 1}}
    assert with_lines("value=5").part.setting == 1 and with_lines().value == 1
    assert with_lines("other.x=2").other.x == 2 and with_lines().other.x == 1
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "y.yaml").write_text("z: 9\n")
    assert with_lines("+other=y").other == {"x": 1, "z": 9}
