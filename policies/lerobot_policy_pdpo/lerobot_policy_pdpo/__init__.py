"""PDPO as a lerobot policy plugin: ``--policy.type=pdpo``.

``configuration_pdpo`` (every hyperparameter), ``modeling_pdpo`` (the diffusion actor:
crowd encoder + denoiser + reverse process, and the lerobot wrapper), ``processor_pdpo`` (normalization in, denormalization out).
"""

from .configuration_pdpo import PDPOConfig
from .modeling_pdpo import PDPOPolicy
from .processor_pdpo import make_pdpo_pre_post_processors

__all__ = ["PDPOConfig", "PDPOPolicy", "make_pdpo_pre_post_processors"]
