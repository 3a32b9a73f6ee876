"""CrowdNav++ as a lerobot policy plugin: ``--policy.type=crowdnavpp``.

``configuration_crowdnavpp`` (the reference sizes), ``modeling_crowdnavpp`` (the attention-graph
recurrent actor-critic of Liu et al., ICRA 2023, and the lerobot wrapper), ``processor_crowdnavpp``
(identity: the network reads raw metres and m/s, as the reference does). Trained by PPO
(``lerobot-crowdnav-train-ppo``); it has no supervised loss.
"""

from .configuration_crowdnavpp import CrowdNavPPConfig
from .modeling_crowdnavpp import CrowdNavPPPolicy
from .processor_crowdnavpp import make_crowdnavpp_pre_post_processors

__all__ = ["CrowdNavPPConfig", "CrowdNavPPPolicy", "make_crowdnavpp_pre_post_processors"]
