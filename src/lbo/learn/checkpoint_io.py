"""Checkpoints written whole or not at all.

Lightning writes a checkpoint straight into its file, so a run killed while it writes
``last.ckpt`` would leave a torn file for ``resume=true`` to trip over. Here each checkpoint
goes to a temp file beside it and is renamed into place once complete (:mod:`lbo.core.atomic`).
"""

from __future__ import annotations

from typing import Any

from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from lbo.core.atomic import atomic_path


class AtomicCheckpointIO(TorchCheckpointIO):
    """:class:`TorchCheckpointIO` whose files appear complete, by a rename, or not at all."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any,
                        storage_options: Any | None = None) -> None:
        with atomic_path(path) as tmp:
            super().save_checkpoint(checkpoint, tmp, storage_options)
