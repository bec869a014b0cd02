"""The actor-critic network: encoder → memory → actor head and critic head(s) (paper appendix).

Actor: `Dense(h, h) → ReLU → Dense(h, A)` (tanh instead of ReLU for continuous actions), then a categorical
(with the observation's action mask) or a diagonal Gaussian with a state-independent log-std. Critic:
`Dense(h, h) → ReLU → Dense(h, 1)`; λ-discrepancy uses two critic heads on the same trunk.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray, PyTree

from ..env import AbstractEnvironment, Box, DictSpace, Discrete, action_mask, observation_array
from .._backend import Backend
from ..memory import GRU, AbstractMemory, Dense, Memoryless, TransformerXL, memory_class
from ._config import ConfigError, TrainConfig
from ._distributions import Categorical, DiagGaussian
from ._encoders import MLPEncoder, make_encoder


class Head(eqx.Module):
    """`Dense → activation → Dense`."""

    hidden: Dense
    out: Dense
    activation: str = eqx.field(static=True)

    def __init__(self, size: int, out_size: int, *, key: PRNGKeyArray, out_scale: float, activation: str = "relu"):
        k1, k2 = jax.random.split(key)
        self.hidden = Dense(size, size, key=k1)
        self.out = Dense(size, out_size, key=k2, scale=out_scale)
        self.activation = activation

    def __call__(self, x: Float[Array, "*b h"]) -> Float[Array, "*b out"]:
        act = jnp.tanh if self.activation == "tanh" else jax.nn.relu
        return self.out(act(self.hidden(x)))


def memory_options(cfg: TrainConfig, backend: Backend = Backend()) -> dict:
    """The constructor options of `cfg.memory`'s class beyond `(in_size, hidden_size, key=key)`: the one place that
    maps `TrainConfig`'s fields (and the backend's choices, `pobax._backend.Backend`) to memories. The GRU and LSTM
    take their loops' `unroll` (`cfg.unroll`, else the backend's), `impl` and `platform`, the GRU `extra_dense`, the
    Transformer-XL its sizes; the zoo's other cells and a user's none."""
    unroll = cfg.unroll if cfg.unroll is not None else backend.scan_unroll()
    if cfg.memory == "gru":
        return dict(extra_dense=cfg.extra_dense, unroll=unroll, impl=backend.gru(cfg.hidden_size),
                    platform=backend.platform)
    if cfg.memory == "lstm":
        return dict(unroll=unroll, impl=backend.lstm(cfg.hidden_size), platform=backend.platform)
    if cfg.memory == "trxl":
        return dict(embed_size=cfg.embed_size, num_heads=cfg.num_heads, num_layers=cfg.num_layers,
                    qkv_features=cfg.qkv_features, window_mem=cfg.window_mem, window_grad=cfg.window_grad,
                    gating=cfg.gating, gating_bias=cfg.gating_bias)
    return {}


#: The TrainConfig fields that one kind of agent alone reads, each with that agent and the flag that chooses it: the
#: Transformer-XL's sizes and the GRU's extra layer (`memory_options`), λ-discrepancy's second λ, β and advantage mix
#: (`ppo_loss` and the advantages in `update`, read only with two critics), which previous action is appended
#: (`make_env`, only with `action_concat`).
AGENT_FIELDS: dict[str, tuple[str, str]] = {
    **{f: ("the Transformer-XL memory", "--memory trxl") for f in (
        "embed_size", "num_heads", "num_layers", "qkv_features", "window_mem", "window_grad", "gating")},
    "gating_bias": ("the Transformer-XL memory's gates", "--memory trxl --gating"),
    "extra_dense": ("the GRU memory", "--memory gru"),
    **{f: ("the λ-discrepancy agent", "--double-critic") for f in ("lambda1", "ld_weight", "alpha")},
    "previous_action": ("an agent given the previous action", "--action-concat"),
}


def unread_fields(cfg: TrainConfig | dict, fields) -> dict[str, tuple[str, str]]:
    """Those of `fields` (TrainConfig field names) that `cfg`'s agent does not read, each with the agent that would
    and the flag that chooses it (`AGENT_FIELDS`): `train --memory gru --ld-weight 0.5` trains no λ-discrepancy.
    `cfg` may be a run's saved configuration (a dict, `config.json`'s "config")."""
    value = cfg.get if isinstance(cfg, dict) else lambda k, default=None: getattr(cfg, k)
    memory, gating = value("memory"), value("gating", True) is True
    reads = {"--memory trxl": memory == "trxl", "--memory trxl --gating": memory == "trxl" and gating,
             "--memory gru": memory == "gru", "--double-critic": value("double_critic") is True,
             "--action-concat": value("action_concat") is True}
    return {f: AGENT_FIELDS[f] for f in fields if f in AGENT_FIELDS and not reads[AGENT_FIELDS[f][1]]}


#: What a gap report or benchmark adds to read a field `unread_fields` names, by the flag that makes an agent read it.
_READER = {"--memory trxl": "add trxl to --agents", "--memory trxl --gating": "add trxl to --agents",
           "--memory gru": "add gru (or ld) to --agents", "--double-critic": "add ld to --agents",
           "--action-concat": "add --action-concat"}


def unread_by_all(configs: list, fields) -> dict[str, tuple[str, str]]:
    """Those of `fields` that no configuration of `configs` reads (`unread_fields`), in the order given."""
    return {f: AGENT_FIELDS[f] for f in fields if configs and all(unread_fields(c, [f]) for c in configs)}


def check_overrides_read(configs: list[tuple[str, object]], overrides, error=ValueError) -> None:
    """Refuse an override that no agent of `configs` ((agent name, TrainConfig) pairs) reads (`unread_fields`):
    `--ld-weight` for agents without the λ-discrepancy one, a Transformer-XL size without `trxl` among them."""
    unread = unread_by_all([c for _, c in configs], sorted(overrides or {}))
    if unread:
        f, (who, flag) = next(iter(unread.items()))
        raise error(f"--{f.replace('_', '-')} is read only by {who}, and no agent trained here has it "
                    f"({', '.join(dict.fromkeys(n for n, _ in configs))}): {_READER[flag]}, or "
                    f"drop --{f.replace('_', '-')}.")


def make_memory(name: str, in_size: int, hidden_size: int, *, key: PRNGKeyArray, **options) -> AbstractMemory:
    """Build a memory cell by name (`pobax.memory.MEMORIES`) or `package.module:ClassName`, as
    `Class(in_size, hidden_size, key=key, **options)` (`memory_options`; the Transformer-XL's width is its
    `embed_size`, so it is built as `TransformerXL(in_size, key=key, **options)`)."""
    cls = memory_class(name)  # raises ValueError for an unknown name or a bad package.module:ClassName
    if cls is TransformerXL:
        return TransformerXL(in_size, key=key, **options)
    try:
        cell = cls(in_size, hidden_size, key=key, **options)
    except TypeError as e:
        if "abstract class" not in str(e):  # an error in the cell's own code is the cell's: its traceback stays
            raise
        raise ConfigError(f"Memory {name!r}: {str(e).splitlines()[0]}; a memory defines in_size and out_size "
                          f"(pobax.memory.AbstractMemory; examples/custom_memory.py).") from None
    if not isinstance(cell, AbstractMemory):
        raise TypeError(f"Memory {name!r}: {cls.__name__}(in_size, hidden_size, key=key) returned a {type(cell).__name__}, "
                        f"not a pobax.memory.AbstractMemory.")
    for attr in ("in_size", "out_size"):
        v = getattr(cell, attr)
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 2**31 - 1:
            raise ConfigError(f"Memory {name!r}: {cls.__name__}.{attr} is {v!r}; it must be a positive integer of at "
                              f"most {2**31 - 1:,} (the width of the cell's inputs or outputs).")
    if cell.in_size != in_size:
        raise ConfigError(f"Memory {name!r}: {cls.__name__}.in_size is {cell.in_size}, but it was built for inputs of "
                          f"{in_size} (its first argument); return that argument as in_size.")
    return cell


class ActorCritic(eqx.Module):
    encoder: eqx.Module
    memory: AbstractMemory
    actor: Head
    critics: tuple[Head, ...]
    log_std: Float[Array, " act"] | None
    continuous: bool = eqx.field(static=True)

    def __init__(
        self,
        env: AbstractEnvironment,
        *,
        key: PRNGKeyArray,
        memory: str = "gru",
        hidden_size: int = 128,
        num_critics: int = 1,
        encoder: str = "auto",
        **options,
    ):
        k_enc, k_mem, k_act, k_crit = jax.random.split(key, 4)
        obs_space = env.observation_space
        if isinstance(obs_space, DictSpace):
            obs_space = obs_space["obs"]
        self.encoder = make_encoder(obs_space.shape, hidden_size, key=k_enc, kind=encoder)
        self.memory = make_memory(memory, self.encoder.out_size, hidden_size, key=k_mem, **options)
        feat = self.memory.out_size
        space = env.action_space
        if isinstance(space, Discrete):
            self.continuous = False
            n_act = space.n
            self.log_std = None
        elif isinstance(space, Box):
            self.continuous = True
            n_act = math.prod(space.shape)
            self.log_std = jnp.zeros((n_act,), jnp.float32)
        else:
            raise TypeError(f"Unsupported action space {space!r}: expected Discrete or Box.")
        self.actor = Head(feat, n_act, key=k_act, out_scale=0.01, activation="tanh" if self.continuous else "relu")
        self.critics = tuple(Head(feat, 1, key=k, out_scale=1.0) for k in jax.random.split(k_crit, num_critics))

    def init_carry(self) -> PyTree:
        return self.memory.init_carry()

    def __call__(
        self, carry: PyTree, obs: PyTree[Array], starts: Bool[Array, " time"]
    ) -> tuple[PyTree, Categorical | DiagGaussian, Float[Array, "time critics"]]:
        """Process a sequence of observations (leading axis time) of one environment."""
        x = jax.vmap(self.encoder)(observation_array(obs))
        carry, feats = self.memory(carry, x, starts)
        out = self.actor(feats)
        if self.continuous:
            dist = DiagGaussian(out, jnp.broadcast_to(self.log_std, out.shape))
        else:
            dist = Categorical.from_logits(out, action_mask(obs))
        values = jnp.concatenate([c(feats) for c in self.critics], axis=-1)
        return carry, dist, values


def release_init(model: ActorCritic) -> ActorCritic:
    """`model` (memoryless or GRU, built with pobax's PPO initialisation) with the original release's initial gains
    (`TrainConfig.init` "release"), as the saved parameters of PyPI `pobax==0.0.1` show (`docs/parity.md`): along the
    path to the memory's output the first Dense at orthogonal gain 2 and every later one at 0.01, the heads' hidden
    layers at gain 2 (a continuous actor's: √2, as pobax's), a GRU's input weights at standard deviation 1/√hidden.
    Each orthogonal weight is rescaled (gain √2 → the release's), so the draws stay pobax's."""
    if not isinstance(model.memory, (GRU, Memoryless)):
        raise ValueError(f"the release's initialisation is defined for memoryless and GRU agents, not "
                         f"{type(model.memory).__name__}")

    def weights(m):  # the embedding's Dense weights in the order the input meets them, and the heads' hidden ones
        encoder = m.encoder.mlp.layers if isinstance(m.encoder, MLPEncoder) else ()
        inner = m.memory.pre.layers if isinstance(m.memory, GRU) else m.memory.mlp.layers
        heads = [c.hidden for c in m.critics] + ([] if m.continuous else [m.actor.hidden])  # continuous actor: √2
        return [d.weight for d in (*encoder, *inner)], [d.weight for d in heads]

    embed, heads = weights(model)
    gains = [2.0] + [0.01] * (len(embed) - 1) + [2.0] * len(heads)
    model = eqx.tree_at(lambda m: sum(weights(m), []), model,
                        [w * (g / math.sqrt(2.0)) for w, g in zip(embed + heads, gains)])
    if isinstance(model.memory, GRU):  # pobax draws U(±1/√h), standard deviation 1/√(3h)
        model = eqx.tree_at(lambda m: m.memory.weight_ih, model, model.memory.weight_ih * math.sqrt(3.0))
    return model
