"""CrowdNav++ (Liu et al., ICRA 2023; ``selfAttn_merge_srnn``): the attention-graph recurrent
actor-critic, written from the reference's description (docs/crowdnavpp.md), and its lerobot wrapper.

One env step, B envs, N human slots (shapes; sizes of the reference config):

    split_obs(observation.state (B, 269))
      robot (B, 9)        [vx, vy | px, py, r, gx, gy, v_pref, theta]   world frame, m and m/s
      humans (B, N, 12)   positions at k = 0..5 relative to the robot    m, world axes
      visible (B, N)      the first max(1, #visible) slots (sorted prefix; slot 0 always admitted)
    robot_linear          (B, 256)        Linear(9, 256) ReLU
    human_attn            (B, N, 512)     embed 12->128->512, q/k/v linears, 8-head attention, keys masked
    spatial_linear        (B, N, 256)     Linear(512, 256) ReLU
    robot_human_attn      (B, 256)        dot product of 64-d projections x N/sqrt(64), masked softmax,
                                          weighted sum of the human features
    node_rnn              (B, 256)        [ReLU(Linear 256->64)(robot) | ReLU(Linear 256->64)(attended)]
                                          -> GRU 128 (memory (B, 128), zeroed at an episode start) -> Linear 256
    actor / critic        (B, 256)        two Linear+Tanh each
    action_mean (B, 2), value (B,)        Linear(256, 2); Linear(256, 1); std = exp(log_std), state-independent

The reference's ``human_node_final_linear`` (Linear(256, 2), never used in its forward) is left
out: DDP refuses parameters that never get a gradient. ``CrowdNavPPNet.reference_parameter_count``
adds it back for the comparison with the paper's 2.503 M.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn

from lerobot_crowdnav.layout import ROBOT_DIM, SELF_DIM, humans_slice, mask_slice, visible_prefix_groups

from .configuration_crowdnavpp import CrowdNavPPConfig

# The reference's dead Linear(node_output_size, 2), counted by the paper's 2.503 M.
DEAD_HEAD_PARAMETERS = 256 * 2 + 2
# Groups of similar visible counts in which the human self-attention runs (speed only).
HUMAN_BUCKETS = 4


class CrowdNavPPInputs(NamedTuple):
    """CrowdNav++'s observation dict, from ours."""

    robot: Tensor  # (..., 9) cat(temporal_edges (vx, vy), robot_node (px, py, r, gx, gy, v_pref, theta))
    humans: Tensor  # (..., N, 2(L+1)) spatial_edges: positions at k = 0..L minus the robot's, m
    detected: Tensor  # (...,) detected_human_num, clamped to >= 1 (long)
    visible: Tensor  # (..., N) bool: slot i < detected


def split_obs(state: Tensor, num_humans: int, prediction_steps: int) -> CrowdNavPPInputs:
    """observation.state ``(..., D)`` -> CrowdNav++'s robot node, spatial edges and mask.

    The robot 9-vector puts the velocity (the reference's temporal edge) first, as the reference
    concatenates it. Visible humans come first in our layout (sorted by distance), so the count
    reproduces the reference's prefix mask; with nobody visible the count is 1 and slot 0 (a
    sentinel row) is attended, as the reference env does (an all-masked row would give NaN)."""
    robot = torch.cat([state[..., ROBOT_DIM:SELF_DIM], state[..., :ROBOT_DIM]], dim=-1)
    humans = state[..., humans_slice(num_humans, prediction_steps)].unflatten(-1, (num_humans, -1))
    detected = state[..., mask_slice(num_humans, prediction_steps)].sum(-1).round().long().clamp(min=1)
    visible = torch.arange(num_humans, device=state.device) < detected[..., None]
    return CrowdNavPPInputs(robot, humans, detected, visible)


def compose_affine(w2: Tensor, b2: Tensor, w1: Tensor, b1: Tensor) -> tuple[Tensor, Tensor]:
    """``x -> W2 (W1 x + b1) + b2`` as one affine map ``(W2 W1, W2 b1 + b2)``; leading batch
    dimensions of the weights ``(..., out, in)`` and biases ``(..., out)`` compose pairwise."""
    return w2 @ w1, (w2 @ b1[..., None])[..., 0] + b2


def _orthogonal(layer: nn.Linear, gain: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


class HumanSelfAttention(nn.Module):
    """Human-human attention (reference ``SpatialEdgeSelfAttn``): an MLP embedding of each
    spatial edge, then separate q/k/v linears in front of ``nn.MultiheadAttention`` (whose own
    in-projection follows: a reference quirk, kept as parameters). Invisible humans are masked as
    keys only; their rows still produce outputs, which the robot-human attention then ignores.

    With more than d human rows (a PPO minibatch: a few thousand), the two affine maps in a row
    are applied as one, ``W_in (W x + b) + b_in = (W_in W) x + (W_in b + b_in)``: composing costs
    d^3 once instead of d^2 per row, so the projections' arithmetic falls by a third. Fewer rows
    (acting) apply them one after the other. Parameters, gradients and outputs (to float
    rounding) are the reference's either way. ``attend`` stops before the out-projection, so that
    a caller may compose it with the linear map that follows (``CrowdNavPPNet.human_features``)."""

    def __init__(self, cfg: CrowdNavPPConfig):
        super().__init__()
        d = cfg.attn_size
        self.embedding = nn.Sequential(nn.Linear(cfg.human_input_size, cfg.human_embed_hidden), nn.ReLU(),
                                       nn.Linear(cfg.human_embed_hidden, d), nn.ReLU())
        self.q_linear, self.k_linear, self.v_linear = nn.Linear(d, d), nn.Linear(d, d), nn.Linear(d, d)
        self.attention = nn.MultiheadAttention(d, cfg.attn_heads, batch_first=True)

    def composed_qkv(self, rows: int) -> tuple[Tensor, Tensor] | None:
        """The q/k/v linears and the in-projection composed, weight (3d, d) and bias (3d,), if
        ``rows`` human rows are to be projected (composing pays above d rows); else None."""
        d = self.attention.embed_dim
        if rows <= d:
            return None
        w_in, b_in = self.attention.in_proj_weight.view(3, d, d), self.attention.in_proj_bias.view(3, d)
        w = torch.stack([self.q_linear.weight, self.k_linear.weight, self.v_linear.weight])
        b = torch.stack([self.q_linear.bias, self.k_linear.bias, self.v_linear.bias])
        weight, bias = compose_affine(w_in, b_in, w, b)
        return weight.flatten(0, 1), bias.flatten()

    def forward(self, humans: Tensor, visible: Tensor, composed: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """humans (B, N, 2(L+1)), visible (B, N) -> (B, N, attn_size); ``composed``: from
        ``composed_qkv`` (computed once for several calls), or None: the two maps in turn."""
        return self.attention.out_proj(self.attend(humans, visible, composed))

    def attend(self, humans: Tensor, visible: Tensor, composed: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """``forward`` without the out-projection: the heads' outputs, concatenated (B, N, attn_size)."""
        e = self.embedding(humans)
        (b, n, d), heads = e.shape, self.attention.num_heads
        if composed is None:
            first = (self.q_linear, self.k_linear, self.v_linear)
            in_proj = zip(self.attention.in_proj_weight.chunk(3), self.attention.in_proj_bias.chunk(3), strict=True)
            qkv = torch.cat([nn.functional.linear(f(e), w, bias) for f, (w, bias) in zip(first, in_proj, strict=True)], -1)
        else:
            qkv = nn.functional.linear(e, *composed)
        q, k, v = qkv.view(b, n, 3, heads, d // heads).permute(2, 0, 3, 1, 4)
        z = nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=visible[:, None, None, :])
        return z.transpose(1, 2).reshape(b, n, d)


class RobotHumanAttention(nn.Module):
    """Robot-human attention (reference ``EdgeAttention_M``, one head): scores
    ``<W_t robot, W_s h_i> * N / sqrt(attention_size)`` (the reference *multiplies* by this
    temperature: 2.5 for N = 20), masked softmax over the N slots, weighted sum of h itself."""

    def __init__(self, cfg: CrowdNavPPConfig):
        super().__init__()
        self.temporal_edge_layer = nn.Linear(cfg.feature_size, cfg.attention_size)
        self.spatial_edge_layer = nn.Linear(cfg.feature_size, cfg.attention_size)
        self.temperature = cfg.num_humans / math.sqrt(cfg.attention_size)

    def forward(self, robot: Tensor, humans: Tensor, visible: Tensor) -> tuple[Tensor, Tensor]:
        """robot (B, F), humans (B, N, F), visible (B, N) -> attended (B, F), weights (B, N)."""
        scores = (self.spatial_edge_layer(humans) * self.temporal_edge_layer(robot)[:, None]).sum(-1)
        weights = (scores * self.temperature).masked_fill(~visible, -1e9).softmax(-1)
        return (weights[..., None] * humans).sum(-2), weights


class NodeRNN(nn.Module):
    """The robot node's GRU (reference ``EndRNN``): embeds the robot features and the attended
    human features (64 each, ReLU), one GRU step, a linear output (no activation)."""

    def __init__(self, cfg: CrowdNavPPConfig):
        super().__init__()
        self.encoder_linear = nn.Linear(cfg.feature_size, cfg.node_embedding_size)
        self.edge_attention_embed = nn.Linear(cfg.feature_size, cfg.node_embedding_size)
        self.gru = nn.GRU(2 * cfg.node_embedding_size, cfg.node_rnn_size)
        for name, p in self.gru.named_parameters():  # reference RNNBase: orthogonal weights, zero biases
            nn.init.orthogonal_(p) if "weight" in name else nn.init.zeros_(p)
        self.output_linear = nn.Linear(cfg.node_rnn_size, cfg.node_output_size)

    def forward(self, robot: Tensor, attended: Tensor, memory: Tensor, starts: Tensor) -> tuple[Tensor, Tensor]:
        """robot, attended (L, M, F); memory (M, H) before step 0; starts (L, M) bool, where the
        memory restarts from zeros -> outputs (L, M, node_output_size), memory after step L-1."""
        x = torch.cat([self.encoder_linear(robot).relu(), self.edge_attention_embed(attended).relu()], -1)
        out = []
        h = memory[None]
        # cuDNN's GRU has no backward outside training mode, and PPO trains this network in eval
        # mode (rollout and update must agree): then the GRU runs on PyTorch's own kernels.
        with cudnn_disabled(not self.training and torch.is_grad_enabled()):
            for t in range(x.shape[0]):
                h = h * ~starts[t, None, :, None]
                y, h = self.gru(x[t:t + 1], h)
                out.append(y)
        return self.output_linear(torch.cat(out)), h[0]


@contextmanager
def cudnn_disabled(disable: bool) -> Iterator[None]:
    """cuDNN off inside the block when ``disable``; every other cuDNN setting untouched."""
    enabled = torch.backends.cudnn.enabled
    torch.backends.cudnn.enabled = enabled and not disable
    try:
        yield
    finally:
        torch.backends.cudnn.enabled = enabled


class CrowdNavPPNet(nn.Module):
    """The whole actor-critic: ``unroll`` scores sequences, ``step`` acts."""

    def __init__(self, cfg: CrowdNavPPConfig):
        super().__init__()
        self.cfg = cfg
        sqrt2 = math.sqrt(2)
        self.robot_linear = nn.Sequential(_orthogonal(nn.Linear(cfg.robot_input_size, cfg.feature_size), sqrt2), nn.ReLU())
        self.human_attn = HumanSelfAttention(cfg)
        self.spatial_linear = nn.Sequential(_orthogonal(nn.Linear(cfg.attn_size, cfg.feature_size), sqrt2), nn.ReLU())
        self.robot_human_attn = RobotHumanAttention(cfg)
        self.node_rnn = NodeRNN(cfg)
        hid = cfg.head_hidden_size
        self.actor = nn.Sequential(_orthogonal(nn.Linear(cfg.node_output_size, hid), sqrt2), nn.Tanh(),
                                   _orthogonal(nn.Linear(hid, hid), sqrt2), nn.Tanh())
        self.critic = nn.Sequential(_orthogonal(nn.Linear(cfg.node_output_size, hid), sqrt2), nn.Tanh(),
                                    _orthogonal(nn.Linear(hid, hid), sqrt2), nn.Tanh())
        self.critic_linear = _orthogonal(nn.Linear(hid, 1), sqrt2)
        self.action_mean = _orthogonal(nn.Linear(hid, 2), 1.0)
        self.log_std = nn.Parameter(torch.full((2,), cfg.init_log_std))

    def encode(self, state: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The part without recurrence, for any batch of observations ``(B, D)``: robot
        features (B, F), attended human features (B, F), robot-human attention weights (B, N)."""
        obs = split_obs(state, self.cfg.num_humans, self.cfg.prediction_steps)
        robot = self.robot_linear(obs.robot)
        n = int(obs.detected.max())
        humans = self.human_features(obs.humans[:, :n], obs.visible[:, :n], obs.detected)
        attended, weights = self.robot_human_attn(robot, humans, obs.visible[:, :n])
        return robot, attended, nn.functional.pad(weights, (0, self.cfg.num_humans - n))

    def human_features(self, humans: Tensor, visible: Tensor, detected: Tensor) -> Tensor:
        """Self-attention and spatial linear of the visible humans only: ``(B, n, F)``, the rows
        past a group's largest count left zero. Visible humans are a prefix and nothing reads the
        other rows (masked as keys here and in the robot-human attention), so the batch is cut
        into ``HUMAN_BUCKETS`` groups of similar counts, each padded only to its own largest
        count: the same values as running all N slots, at a fraction of the arithmetic (the
        512-wide attention is most of this network's cost). Large batches also apply the
        attention's out-projection and the spatial linear as one map (``composed_out``)."""
        buckets, back = visible_prefix_groups(detected, HUMAN_BUCKETS)
        rows = sum(len(idx) * k for idx, k in buckets)
        composed, out = self.human_attn.composed_qkv(rows), self.composed_out(rows)
        parts = []
        for idx, k in buckets:
            z = self.human_attn.attend(humans[idx, :k], visible[idx, :k], composed)
            if out is None:
                z = self.spatial_linear(self.human_attn.attention.out_proj(z))
            else:
                z = nn.functional.linear(z, *out).relu()
            parts.append(nn.functional.pad(z, (0, 0, 0, humans.shape[1] - k)))
        return torch.cat(parts)[back]

    def composed_out(self, rows: int) -> tuple[Tensor, Tensor] | None:
        """The attention's out-projection and ``spatial_linear``'s Linear (no activation between
        them) as one map, weight (F, d) and bias (F,), if ``rows`` human rows are to be mapped:
        composing costs F d^2 once and saves d^2 per row, so it pays above F rows; else None."""
        if rows <= self.cfg.feature_size:
            return None
        out_proj, linear = self.human_attn.attention.out_proj, self.spatial_linear[0]
        return compose_affine(linear.weight, linear.bias, out_proj.weight, out_proj.bias)

    def unroll(self, state: Tensor, memory: Tensor, starts: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """M sequences of L observations ``(L, M, D)`` from memory ``(M, H)``, restarting where
        ``starts (L, M)`` -> action mean (L, M, 2), value (L, M), the memory after the last step."""
        L, M = state.shape[:2]
        robot, attended, _ = self.encode(state.reshape(L * M, -1))  # every step at once
        x, memory = self.node_rnn(robot.view(L, M, -1), attended.view(L, M, -1), memory, starts)
        return self.action_mean(self.actor(x)), self.critic_linear(self.critic(x)).squeeze(-1), memory

    def step(self, state: Tensor, memory: Tensor, starts: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """One step of B envs: state (B, D), memory (B, H) -> mean (B, 2), value (B,), memory."""
        starts = torch.zeros(1, state.shape[0], dtype=torch.bool, device=state.device) if starts is None else starts[None]
        mean, value, memory = self.unroll(state[None], memory, starts)
        return mean[0], value[0], memory

    def initial_memory(self, batch_size: int) -> Tensor:
        return torch.zeros(batch_size, self.cfg.node_rnn_size, device=self.log_std.device)

    def parameter_counts(self) -> dict[str, int]:
        trainable = sum(p.numel() for p in self.parameters() if p.requires_grad)
        return {"trainable": trainable, "reference_with_dead_head": trainable + DEAD_HEAD_PARAMETERS}


class CrowdNavPPPolicy(PreTrainedPolicy):
    """CrowdNav++ for lerobot. ``select_action`` / ``predict_action_chunk`` act deterministically
    (the Gaussian's mean, as the reference's evaluation) and carry a (B, node_rnn_size) GRU
    memory from call to call; ``reset()`` clears it, and ``episode_start`` (B,) bool zeroes the
    rows of envs whose episode just began. Trained by PPO only: ``forward`` has no loss."""

    config_class = CrowdNavPPConfig
    name = "crowdnavpp"
    recurrent = True

    def __init__(self, config: CrowdNavPPConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.net = CrowdNavPPNet(config)
        self.reset()

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Always strict: missing weights must not load as random ones."""
        return super()._load_as_safetensor(model, model_file, map_location, True)

    def _save_pretrained(self, save_directory, state_dict: dict[str, Tensor] | None = None) -> None:
        """Each weight saved as its own copy: on a GPU, cuDNN packs the GRU's weights into one
        buffer they are views of, which safetensors refuses to save."""
        if state_dict is None:
            state_dict = {k: v.detach().clone() for k, v in self.state_dict().items()}
        super()._save_pretrained(save_directory, state_dict=state_dict)

    def get_optim_params(self) -> list[nn.Parameter]:
        return list(self.parameters())

    def reset(self) -> None:
        self._memory: Tensor | None = None

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        raise NotImplementedError("crowdnavpp is an RL policy with no supervised loss: train it with PPO "
                                  "(lerobot-crowdnav-train-ppo --policy.type=crowdnavpp), not lerobot-train")

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The next action of each env ``(B, 1, 2)`` in m/s (the mean), advancing the memory.
        ``episode_start`` (B,) bool: envs whose memory restarts; a new batch size restarts all."""
        state = batch[OBS_STATE]
        b = state.shape[0]
        if self._memory is None or self._memory.shape[0] != b:
            self._memory = self.net.initial_memory(b)
        starts = kwargs.get("episode_start")
        starts = None if starts is None else torch.as_tensor(starts, dtype=torch.bool, device=state.device)
        mean, _, self._memory = self.net.step(state, self._memory, starts)
        return mean[:, None]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The next action ``(B, 2)`` in m/s."""
        return self.predict_action_chunk(batch, **kwargs)[:, 0]

    def parameter_counts(self) -> dict[str, int]:
        """Trainable parameters (2,502,021 at the reference sizes) and the reference network's
        count with its unused head (2,502,535: the paper's 2.503 M)."""
        return self.net.parameter_counts()

