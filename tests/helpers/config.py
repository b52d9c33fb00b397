"""Configs for the tests, composed from conf/ the way the entry points compose them."""

from __future__ import annotations

from hydra import compose, initialize_config_dir

from lbo.core.cli import respell
from lbo.core.paths import CONF_DIR

TRAINING = ("train", "tune")
"""The configs whose command lines take the short model keys."""


def compose_cfg(name: str, overrides: list[str] | None = None):
    """Compose a config from conf/ the way the entry points do, without running Hydra: a
    training config (``train``, ``tune``) reads ``window=`` as ``model.window=`` (and the
    other short model keys, :func:`lbo.core.cli.respell`), as their command lines do."""
    overrides = list(overrides or [])
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose(config_name=name,
                       overrides=respell(overrides) if name in TRAINING else overrides)


def train_cfg(tmp_path, smoke_data, *overrides):
    """The training config at smoke scale, writing under ``tmp_path / 'out'`` (no ONNX graphs
    kept for ``lbo.observe``: seconds per run)."""
    return compose_cfg("train", ["experiment=smoke", "keep_onnx=false",
                                 f"data.root={smoke_data.parent}",
                                 f"output_dir={tmp_path / 'out'}", *overrides])


ROBUST_SMOKE = ("experiment=robust", "data=smoke", "trainer.max_epochs=1")
"""The robust experiment cut to one short epoch on the smoke sets (add the batches, the
window and the batch size)."""


SWEEP_BUDGET = ("trainer.limit_train_batches=5",)
"""The paper sweep's budget beyond experiment=smoke (its two epochs, five batches each:
``paper_sweep`` in conftest); a sweep compared with it runs the same."""
