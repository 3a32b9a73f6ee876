"""Model size of a PDPO checkpoint, as the report's parameter table and the hub model card show it."""

from __future__ import annotations

import math
from pathlib import Path

from ..checkpoint_files import CRITIC


def parameter_counts(weights: Path) -> dict[str, int]:
    """Actor and critic sizes of a PDPO checkpoint: the actor in ``model.safetensors``, the
    critic in ``critic.safetensors`` beside it (fine-tuned; none for BC). Checkpoints from before
    the actor/critic split hold ``encoder``/``denoiser``/``value`` in ``model.safetensors``."""
    from safetensors import safe_open

    counts = {"actor": 0, "critic": 0}
    critic_file = Path(weights).with_name(CRITIC)
    for path, critic_prefix in ((Path(weights), "value."), (critic_file, "")):
        if not path.exists():
            continue
        with safe_open(str(path), "pt") as f:
            for key in f.keys():
                numel = math.prod(f.get_slice(key).get_shape())
                if key.startswith(("actor.", "encoder.", "denoiser.")):
                    counts["actor"] += numel
                elif key.startswith(critic_prefix):
                    counts["critic"] += numel
    return counts
