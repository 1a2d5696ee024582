"""PPO hyper-parameters and the named presets (`paper` = the paper's Table II)."""

from __future__ import annotations

import dataclasses

from jaxnav.core.checks import require_finite
from jaxnav.ppo.networks import CRITIC_OUTPUTS


def _flag(name: str) -> str:
    """The command-line flag of PPOConfig field `name`: errors name it as the user typed it."""
    return "--" + name.replace("_", "-")


MIN_RESET_POOL = 8  # the fewest new episodes drawn per step (`PPOConfig.reset_pool`)


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Hyper-parameters of one training run. Derived sizes are properties."""

    num_envs: int = 256
    """Robots simulated in parallel."""
    total_steps: int = 3_000_000
    """Environment steps (all robots together) to train for; rounded down to whole updates."""
    rollout_length: int = 32
    """Horizon T: control steps per robot between two updates (Table II: 100)."""
    num_epochs: int = 4
    """Passes of SGD over each rollout (Table II: 10)."""
    minibatch_size: int = 2048
    """Transitions per gradient step (Table II batch size: 128); must divide num_envs * rollout."""
    learning_rate: float = 1e-3
    """Adam step size (Table II: 0.001)."""
    anneal_lr: bool = False
    """Decay the learning rate linearly to 0 over training."""
    gamma: float = 0.99
    """Discount factor (Table II: 0.99)."""
    gae_lambda: float = 0.95
    """GAE parameter lambda (Table II: 0.95)."""
    clip_eps: float = 0.2
    """Clipping parameter epsilon of the surrogate (Table II: 0.2)."""
    vf_coef: float = 0.5
    """Weight of the value loss."""
    ent_coef: float = 0.01
    """Weight of the entropy bonus."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip."""
    clip_value: bool = False
    """PPO value clipping with clip_eps (slows the critic when returns reach -100)."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the actor and critic MLPs (paper: 2 x 64, LeakyReLU)."""
    critic_output: str = "linear"
    """'tanh' (paper: values in [-1, 1]) or 'linear' (unbounded, fits Table I's -100)."""
    reward_scale: float = 1.0
    """Rewards are multiplied by this for learning (use 0.01 with a tanh critic); logs stay raw."""
    privileged_critic: bool = False
    """Give the critic the task's training-only features too (`state.info["critic"]`, e.g. the
    goal task's distance to go along the free space); the actor, and so the exported policy,
    sees the observation only."""
    normalize_obs: bool = True
    """Standardise observations with running mean/variance."""
    reset_share: float = 0.0625
    """New episodes drawn per step for the robots whose episode ended, as a share of num_envs
    (at least 8, or every robot; 1: one per robot; the goal task's own default is 1/64, as its
    resets flood the room). See `jaxnav.wrappers.AutoReset`."""
    reset_ahead: bool = True
    """Draw the new episodes of a whole rollout at its start, in one batch of rollout_length x
    pool draws, instead of a pool at every step: the same distribution from other keys (see
    `jaxnav.wrappers.AutoReset.draw`). The task's reset then compiles once, in the draws'
    program, rather than in init's and the rollout's (docs/results.md, "What was decided and
    why"); false: a pool at every step, in the rollout."""
    reset_in_place: bool = False
    """Write the new episodes into the rows of the robots that finished only, instead of selecting
    between old and new state for every robot: the same result bit for bit (tested; see
    `jaxnav.wrappers.AutoReset`), less memory traffic per step but a branch on every step, which
    a GPU waits for (and several GPUs agree on); off, PPO runs faster and compiles sooner on one
    GPU and on two, and the same on a CPU (docs/results.md, "What was decided and why")."""
    threefry_kernel: bool = False
    """On one GPU, call jax.random's threefry as JAX's CUDA kernel in every program instead of
    inlining its rounds in the rollout and the learner (`jaxnav.core.xla.threefry_kernel`, set by
    `make_train` for the process; the draws, start and init call the kernel on one GPU either
    way): the same random bits in a smaller program. Inlined, the rollout is faster for both
    tasks: the kernel's calls cannot fuse with the step around them (docs/results.md, "What was
    decided and why")."""
    deterministic: bool = False
    """On a GPU, compile with XLA's deterministic ops (`jaxnav.core.xla.deterministic`, set by
    `make_train` for the process), so that one seed trains to the same bits on one machine; off,
    XLA times its kernels per process and some sums add in the order threads finish, so two runs
    of a seed differ. On one H200 the goal task's PPO runs at 13.0 M env-steps/s with it against
    16.0 M (docs/results.md, "One seed, one policy, on a GPU"). The CPU's programs are always so."""
    fusion_autotune: bool = True
    """On a GPU, XLA times the Triton and its own kernels of some fusions (reductions, softmaxes)
    as it compiles (`jaxnav.core.xla.fusion_autotune`, set by `make_train` for the process); the
    goal task turns it off: on one H200 host it then started 2 s sooner, on another no sooner,
    and its gpu preset trained 1-2 % slower, while `avoid` started no sooner and trained 1.6 %
    slower (docs/results.md). No effect on the CPU."""
    fused_learner: bool = True
    """On GPUs, compute each minibatch's gradient as one kernel (`jaxnav.ppo.fused`: the same
    loss, the gradient to the GPU's TF32 rounding) where it applies: a categorical actor whose
    inputs and layers are at most 64 wide, each GPU's rows of a minibatch at least 16,384 and a
    multiple of 64; False: XLA's kernels of `jax.grad`."""
    groups: int = 0
    """Independent blocks the robots are split into (0: one per device). Each block draws its own
    new episodes (`jaxnav.wrappers.AutoReset`) and each minibatch takes the same share of every
    block's transitions, so a device never needs another's robots. Results depend on `groups`, not
    on the device count: two devices give what one gives with groups 2."""
    updates_per_chunk: int = 10
    """Updates per jitted call; progress, metrics and checkpoints happen between chunks. A chunk
    runs only the updates `total_steps` has left."""
    checkpoint_every: int = 50
    """Write a checkpoint every this many updates (and at the end)."""

    def __post_init__(self):
        positive = (
            "num_envs",
            "total_steps",
            "rollout_length",
            "num_epochs",
            "minibatch_size",
            "updates_per_chunk",
            "checkpoint_every",
        )
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{_flag(name)}: must be >= 1, got {getattr(self, name)}")
        if self.batch_size % self.minibatch_size:
            near = sorted(divisors(self.batch_size), key=lambda d: abs(d - self.minibatch_size))
            raise ValueError(
                f"--minibatch-size {self.minibatch_size} must divide --num-envs x --rollout-length = "
                f"{self.num_envs} x {self.rollout_length} = {self.batch_size}; values that do: "
                f"{', '.join(map(str, sorted(near[:4])))}"
            )
        if self.total_steps < self.batch_size:
            raise ValueError(
                f"--total-steps {self.total_steps} is less than one rollout "
                f"(--num-envs x --rollout-length = {self.batch_size})"
            )
        require_finite(self, _flag)
        for name in ("gamma", "gae_lambda"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{_flag(name)}: must be in [0, 1], got {getattr(self, name)}")
        for name in ("learning_rate", "clip_eps", "max_grad_norm", "reward_scale"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{_flag(name)}: must be > 0, got {getattr(self, name)}")
        if self.groups < 0:  # what must divide into blocks: `jaxnav.ppo.train.block_count`
            raise ValueError(f"--groups: must be >= 0 (0: one per device), got {self.groups}")
        if not 0 < self.reset_share <= 1:
            raise ValueError(f"--reset-share: must be in (0, 1], got {self.reset_share}")
        for name in ("vf_coef", "ent_coef"):
            if getattr(self, name) < 0:
                raise ValueError(f"{_flag(name)}: must be >= 0, got {getattr(self, name)}")
        if self.critic_output not in CRITIC_OUTPUTS:
            raise ValueError(
                f"--critic-output: must be one of {', '.join(CRITIC_OUTPUTS)}, "
                f"got {self.critic_output!r}"
            )
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(
                f"--hidden: need at least one layer, each of >= 1 unit, got {list(self.hidden)}"
            )

    @property
    def batch_size(self) -> int:
        """Transitions per update."""
        return self.num_envs * self.rollout_length

    @property
    def num_minibatches(self) -> int:
        return self.batch_size // self.minibatch_size

    @property
    def reset_pool(self) -> int:
        """New episodes drawn per step: `reset_share` of the robots, and at least 8 (or all of
        them): a small batch would otherwise restart most robots that finish together in the
        same episode."""
        return max(min(MIN_RESET_POOL, self.num_envs), round(self.reset_share * self.num_envs))

    @property
    def num_updates(self) -> int:
        return self.total_steps // self.batch_size


PRESETS: dict[str, dict] = {
    # Table II: one robot, 1,500 updates of horizon 100, tanh critic. Its batch of 128 exceeds
    # the 100 transitions one robot collects per horizon, so each SGD step takes the whole rollout.
    "paper": dict(
        num_envs=1,
        total_steps=150_000,
        rollout_length=100,
        num_epochs=10,
        minibatch_size=100,
        learning_rate=1e-3,
        gamma=0.99,
        gae_lambda=0.95,
        clip_eps=0.2,
        critic_output="tanh",
        normalize_obs=False,
        updates_per_chunk=25,
        checkpoint_every=250,
    ),
    # The default: hundreds of robots, solves the task on a 2-core CPU in minutes.
    "cpu": dict(),
    # Thousands of robots on one accelerator.
    "gpu": dict(
        num_envs=8192,
        total_steps=100_000_000,
        rollout_length=32,
        minibatch_size=16384,
        num_epochs=4,
        updates_per_chunk=20,
        checkpoint_every=100,
    ),
}


def preset(name: str, **overrides) -> PPOConfig:
    """The named preset with `overrides` applied; unknown names list the valid ones."""
    if name not in PRESETS:
        raise ValueError(f"--preset: unknown preset '{name}'; valid: {', '.join(PRESETS)}")
    return PPOConfig(**{**PRESETS[name], **overrides})


def divisors(n: int) -> list[int]:
    """The divisors of n >= 1, ascending."""
    small = [d for d in range(1, int(n**0.5) + 1) if n % d == 0]
    return sorted({*small, *(n // d for d in small)})


def derived_minibatch(base: PPOConfig, num_envs: int, rollout_length: int) -> int:
    """The minibatch size for a batch of `num_envs` x `rollout_length` when the user set none:
    the batch split into `base`'s number of minibatches, or the nearest split that divides it."""
    batch = num_envs * rollout_length
    want = max(1, batch // base.num_minibatches)
    return min(divisors(batch), key=lambda d: (abs(d - want), -d))
