"""CrowdNav++ configuration: the sizes of the reference network (``selfAttn_merge_srnn`` of
Shuijing725/CrowdNav_Prediction_AttnGraph, ``arguments.py`` defaults; docs/crowdnavpp.md).

Not to be confused with the simulator preset ``--env.preset=crowdnavpp`` (CrowdNav++'s scene:
robot radius 0.3 m, 5 m sensing): this is the *policy* type ``--policy.type=crowdnavpp``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamConfig

from lerobot_crowdnav.layout import check_policy_features, SELF_DIM, human_row_dim, obs_dim


@PreTrainedConfig.register_subclass("crowdnavpp")
@dataclass
class CrowdNavPPConfig(PreTrainedConfig):
    """CrowdNav++: a robot node, human-human self-attention over the spatial edges, robot-human
    attention, a GRU node and Gaussian actor / value heads on its output.

    The input is ``observation.state``, the 269-float crowd observation of lerobot-crowdnav
    (``[robot 7 | velocity 2 | humans N x 2(L+1) | mask N]``), read raw (metres, m/s); the output
    is one world-frame velocity (vx, vy) in m/s per step, unbounded (the env clips it by norm).
    The policy is recurrent: ``reset()`` clears its GRU memory.
    """

    # -- inputs / outputs --------------------------------------------------------------------
    n_obs_steps: int = 1
    horizon: int = 1
    n_action_steps: int = 1
    # Crowd layout of observation.state: human slots N and constant-velocity prediction steps L
    # (reference: 20 humans, 5 steps, so 2(L+1) = 12 floats per spatial edge).
    num_humans: int = 20
    prediction_steps: int = 5
    # The reference normalizes neither observations nor actions.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {"STATE": NormalizationMode.IDENTITY, "ACTION": NormalizationMode.IDENTITY})

    # -- network (reference arguments.py / selfAttn_srnn_temp_node.py) ------------------------
    # Robot embedding and human feature width (human_human_edge_rnn_size: 256).
    feature_size: int = 256
    # Human-human self-attention: embedding MLP 2(L+1) -> 128 -> attn_size, 8 heads (hard-coded).
    human_embed_hidden: int = 128
    attn_size: int = 512
    attn_heads: int = 8
    # Robot-human attention: both sides projected to attention_size (64) for a dot product.
    attention_size: int = 64
    # Node GRU: inputs embedded to 2 x node_embedding_size (64 each), hidden 128, output 256.
    node_embedding_size: int = 64
    node_rnn_size: int = 128
    node_output_size: int = 256
    # Actor and critic MLPs on the node output: two Tanh layers of this width.
    head_hidden_size: int = 256
    # Initial log-std of the state-independent Gaussian policy (reference: 0, std 1 m/s).
    init_log_std: float = 0.0

    # -- training (reference: one Adam, lr 4e-5, eps 1e-5, no decay; PPO in lerobot_crowdnav.rl) --
    optimizer_lr: float = 4e-5
    optimizer_eps: float = 1e-5
    optimizer_grad_clip_norm: float = 0.5

    def __post_init__(self):
        super().__post_init__()
        if self.n_obs_steps != 1 or self.horizon != 1 or self.n_action_steps != 1:
            raise ValueError("CrowdNav++ reads one observation and outputs one action (n_obs_steps = horizon = "
                             "n_action_steps = 1); its memory is the GRU state")
        if self.attn_size % self.attn_heads:
            raise ValueError("attn_size must be divisible by attn_heads")
        if self.num_humans < 1 or self.prediction_steps < 0:
            raise ValueError("num_humans must be >= 1 and prediction_steps >= 0")

    @property
    def state_dim(self) -> int:
        return obs_dim(self.num_humans, self.prediction_steps)

    @property
    def robot_input_size(self) -> int:
        """The robot node's 9 floats: velocity (2) then px, py, r, gx, gy, v_pref, theta."""
        return SELF_DIM

    @property
    def human_input_size(self) -> int:
        """Floats of one spatial edge: the human's positions at k = 0..L relative to the robot."""
        return human_row_dim(self.prediction_steps)

    def validate_features(self) -> None:
        check_policy_features(self, "CrowdNav++")

    def get_optimizer_preset(self) -> AdamConfig:
        return AdamConfig(lr=self.optimizer_lr, eps=self.optimizer_eps, grad_clip_norm=self.optimizer_grad_clip_norm)

    def get_scheduler_preset(self) -> None:
        return None  # constant learning rate

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None
