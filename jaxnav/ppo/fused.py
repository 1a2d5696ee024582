"""The PPO loss's gradient on GPUs, as one Pallas (Triton) kernel.

XLA computes a minibatch's gradient of the actor-critic as dozens of kernels, each a pass over
[M, width] activations in memory: the forward layers, the loss, and the backward layers of two
MLPs. With the default 64 units that traffic, not the arithmetic, is the learner's time. Here
each program takes `ROWS` transitions and runs the actor forward, the loss's policy and entropy
terms and the actor backward, then the same for the critic and the value term, all in registers;
it writes its share of every weight's gradient and of the loss's sums, which XLA then adds.

The same loss as `losses.ppo_loss` (ties of its min, max and clip split the gradient as JAX's
do), for a categorical actor of LeakyReLU layers; the same gradient to rounding: float32's through
Pallas' interpreter (`tests/test_ppo_core.py`), TF32's on the GPU, where XLA's products multiply
in TF32 too, in another order (`benchmarks/learner.py`). Every
matrix side is padded to a power of two of at least 16 (Triton's smallest product) with zeros,
which add nothing. `make` returns None where it does not apply, and the trainer keeps
`jax.grad(ppo_loss)`. On several GPUs each runs the kernel on its own robots' rows of a minibatch
(`jax.shard_map`): the advantage's mean and spread are joined over the GPUs (one gather), then
the gradient and the loss's sums summed over them (one `lax.psum` of one vector), as XLA's
partitioned `jax.grad` sums its gradient.
"""

from __future__ import annotations

import functools

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, PartitionSpec

from jaxnav.core.xla import pow2
from jaxnav.ppo.distributions import Categorical
from jaxnav.ppo.losses import Batch
from jaxnav.ppo.networks import LEAKY_SLOPE

# Transitions and Triton warps per program: of 32 or 64 rows and 2 or 4 warps, the fastest on one
# H200 at minibatches of 524,288 and 16,384 rows: 1.22 and 0.27 ms against XLA's 1.82 and 0.37 ms
# for the default network (32 rows: 1.45 and 0.27 ms; 2 warps: 2.35-3.31 and 0.37-0.38 ms;
# benchmarks/results/learner_h200.json).
ROWS = 64
WARPS = 4
MAX_WIDTH = 64  # the widest layer (input, hidden or output, padded) a program holds
MIN_ROWS = 16384  # the fewest rows of a minibatch one GPU gives the kernel (the fewest measured)
SUMS = ("surrogate", "value_err", "entropy", "approx_kl", "clipped")  # per-program sums


def _pad(n: int) -> int:
    """n rounded up to a power of two, at least 16 (Triton's smallest product)."""
    return pow2(n, 16)


def _dot_t(a, b):
    """a^T b over their rows: [R, I], [R, O] -> [I, O]."""
    return lax.dot_general(a, b, (((0,), (0,)), ((), ())), preferred_element_type=jnp.float32)


def _dot_bt(a, b):
    """a b^T: [R, O], [I, O] -> [R, I]."""
    return lax.dot_general(a, b, (((1,), (1,)), ((), ())), preferred_element_type=jnp.float32)


def _forward(x, layers):
    """The MLP's output [R, O] and each layer's input and pre-activation (for the backward)."""
    inputs, pre = [x], []
    for w, b in layers[:-1]:
        z = jnp.dot(inputs[-1], w[...], preferred_element_type=jnp.float32) + b[...]
        pre.append(z)
        inputs.append(jnp.where(z >= 0, z, LEAKY_SLOPE * z))  # flax's leaky_relu
    w, b = layers[-1]
    out = jnp.dot(inputs[-1], w[...], preferred_element_type=jnp.float32) + b[...]
    return out, inputs, pre


def _backward(d_out, inputs, pre, layers) -> list:
    """Every layer's weight [I, O] and bias [1, O] gradient, in `layers`' order."""
    grads, d = [], d_out
    for i in reversed(range(len(layers))):
        grads = [_dot_t(inputs[i], d), jnp.sum(d, axis=0, keepdims=True), *grads]
        if i:
            d = _dot_bt(d, layers[i][0][...])
            d = d * jnp.where(pre[i - 1] >= 0, 1.0, LEAKY_SLOPE)
    return grads


def _split(a, b):
    """The share of a in the gradient of min(a, b) (1, 0, or 0.5 on a tie, as JAX's)."""
    return jnp.where(a < b, 1.0, jnp.where(a == b, 0.5, 0.0))


def _inside(x, low, high):
    """The gradient of clip(x, low, high) = min(max(x, low), high) in x (ties: 0.5, as JAX's)."""
    lo = jnp.where(x > low, 1.0, jnp.where(x == low, 0.5, 0.0))
    return lo * _split(jnp.maximum(x, low), jnp.full_like(x, high))


def _actor_terms(xa, act, old_logp, adv, actor, *, actions, eps, ent_coef, scale):
    """The actor's gradients and its sums (surrogate, entropy, approx_kl, clipped) of `ROWS` rows."""
    logits, inputs, pre = _forward(xa, actor)  # [R, Ap]
    col = lax.broadcasted_iota(jnp.int32, logits.shape, 1)
    logits = jnp.where(col < actions, logits, -jnp.inf)
    shifted = logits - jnp.max(logits, axis=1, keepdims=True)
    logp_all = shifted - jnp.log(jnp.sum(jnp.exp(shifted), axis=1, keepdims=True))
    p = jnp.exp(logp_all)
    chosen = col == act[:, None]
    log_ratio = jnp.sum(jnp.where(chosen, logp_all, 0.0), axis=1) - old_logp  # [R]
    ratio = jnp.exp(log_ratio)
    clipped = jnp.clip(ratio, 1.0 - eps, 1.0 + eps)
    s1, s2 = ratio * adv, clipped * adv
    w1 = _split(s1, s2)
    d_ratio = -(w1 + (1.0 - w1) * _inside(ratio, 1.0 - eps, 1.0 + eps)) * adv * scale
    safe_logp = jnp.where(p > 0, logp_all, 0.0)
    ent = -jnp.sum(p * safe_logp, axis=1)  # [R]
    d_logits = (d_ratio * ratio)[:, None] * (jnp.where(chosen, 1.0, 0.0) - p)
    d_logits = d_logits + ent_coef * scale * p * (safe_logp + ent[:, None])
    kl = (ratio - 1.0) - log_ratio
    clip_hit = jnp.where(jnp.abs(ratio - 1.0) > eps, 1.0, 0.0)
    sums = (jnp.minimum(s1, s2), ent, kl, clip_hit)
    return _backward(d_logits, inputs, pre, actor), [jnp.sum(x) for x in sums]


def _critic_terms(xc, old_value, target, critic, *, eps, vf_coef, clip_value, tanh, scale):
    """The critic's gradients and its sum (value_err) of `ROWS` rows."""
    out, inputs, pre = _forward(xc, critic)  # [R, 16]; column 0 is the value
    col = lax.broadcasted_iota(jnp.int32, out.shape, 1)
    u = jnp.sum(jnp.where(col == 0, out, 0.0), axis=1)  # [R]
    if tanh:
        th = jnp.tanh(u)
        value, dv_du = tanh * th, tanh * (1.0 - th * th)
    else:
        value, dv_du = u, 1.0
    err = jnp.square(value - target)
    d_err = 2.0 * (value - target)
    if clip_value:
        step = value - old_value
        v_clip = old_value + jnp.clip(step, -eps, eps)
        err_clip = jnp.square(v_clip - target)
        w = _split(err_clip, err)  # the share of err in max(err, err_clip)
        d_err = w * d_err + (1.0 - w) * 2.0 * (v_clip - target) * _inside(step, -eps, eps)
        err = jnp.maximum(err, err_clip)
    d_u = vf_coef * 0.5 * scale * d_err * dv_du
    grads = _backward(jnp.where(col == 0, d_u[:, None], 0.0), inputs, pre, critic)
    return grads, [jnp.sum(err)]


def _kernel(*refs, n_actor, n_critic, actions, rows, eps, vf_coef, ent_coef, **critic):
    """One program: `ROWS` transitions of a minibatch of `rows`. Writes their gradients' sums and
    the sums of the loss's terms (`SUMS` order)."""
    xa, xc, act, old_logp, old_value, adv, target = (r[...] for r in refs[:7])
    k = 7
    actor = [(refs[k + 2 * i], refs[k + 2 * i + 1]) for i in range(n_actor)]
    k += 2 * n_actor
    critic_layers = [(refs[k + 2 * i], refs[k + 2 * i + 1]) for i in range(n_critic)]
    outs = refs[k + 2 * n_critic :]  # the actor's gradients, the critic's, then the sums
    scale = 1.0 / rows  # every term is a mean over the minibatch
    g_a, (surrogate, ent, kl, clipped) = _actor_terms(
        xa, act, old_logp, adv, actor, actions=actions, eps=eps, ent_coef=ent_coef, scale=scale
    )
    g_c, (value_err,) = _critic_terms(
        xc, old_value, target, critic_layers, eps=eps, vf_coef=vf_coef, scale=scale, **critic
    )
    slot = lax.broadcasted_iota(jnp.int32, outs[-1].shape, 1)
    sums = jnp.zeros(outs[-1].shape, jnp.float32)
    for i, term in enumerate((surrogate, value_err, ent, kl, clipped)):
        sums = jnp.where(slot == i, term, sums)
    for ref, value in zip(outs, [*g_a, *g_c, sums], strict=True):
        ref[...] = value


def _layers(params: dict, name: str) -> list[tuple[jax.Array, jax.Array]]:
    """[(kernel [I, O], bias [O])] of the flax MLP `name`, input layer first."""
    net = params["params"][name]
    return [(net[f"Dense_{i}"]["kernel"], net[f"Dense_{i}"]["bias"]) for i in range(len(net))]


def _padded(layers, first_in: int, out: int):
    """The layers zero-padded to the kernel's sides: input `first_in`, output `out`, hidden
    widths `_pad`-ded; biases as [1, O]."""
    padded, width = [], first_in
    for i, (w, b) in enumerate(layers):
        o = out if i == len(layers) - 1 else _pad(w.shape[1])
        w = jnp.pad(w, ((0, width - w.shape[0]), (0, o - w.shape[1])))
        padded.append((w, jnp.pad(b, (0, o - b.shape[0]))[None]))
        width = o
    return padded


def _unpadded(grads, layers):
    """The programs' gradient shares [P * I, O] (biases [P, O]) summed and cut to `layers`'."""
    out = []
    for (g_w, g_b), (w, b) in zip(zip(grads[::2], grads[1::2], strict=True), layers, strict=True):
        i, o = g_w.shape[0] // g_b.shape[0], g_w.shape[1]
        g_w = g_w.reshape(-1, i, o).sum(0)[: w.shape[0], : w.shape[1]]
        out.append((g_w, g_b.sum(0)[: b.shape[0]]))
    return out


def _tree(actor, critic) -> dict:
    """Gradients in the flax parameters' tree."""
    net = lambda layers: {  # noqa: E731
        f"Dense_{i}": {"kernel": w, "bias": b} for i, (w, b) in enumerate(layers)
    }
    return {"params": {"actor": net(actor), "critic": net(critic)}}


def make(cfg, network, dist, devices, inputs: tuple[int, int], interpret: bool = False):
    """`grad(params, batch) -> (grads, metrics)` as `jax.grad(ppo_loss, has_aux=True)` gives them,
    for `cfg`'s minibatches of `network`'s outputs read by `dist`, on `devices` (each holding
    its robots' rows of every minibatch, as `train.shard_envs` places them), the actor and critic
    reading `inputs` (D, D + C) values; None where the kernel does not apply: off
    (`cfg.fused_learner`), not GPUs (unless `interpret`), not a categorical actor, a layer wider
    than `MAX_WIDTH`, or a device's rows of a minibatch fewer than `MIN_ROWS` or not whole
    programs."""
    gpu = all(d.platform == "gpu" for d in devices)
    categorical = isinstance(dist, Categorical)
    widths = [*inputs, *cfg.hidden, dist.out_size if categorical else MAX_WIDTH + 1]
    rows = cfg.minibatch_size // len(devices)  # each device's
    if not (
        cfg.fused_learner
        and (gpu or interpret)
        and categorical
        and max(_pad(w) for w in widths) <= MAX_WIDTH
        and cfg.minibatch_size % len(devices) == 0
        and rows % ROWS == 0
        and (rows >= MIN_ROWS or interpret)
    ):
        return None
    grad = functools.partial(
        _grad,
        loss=dict(eps=cfg.clip_eps, vf_coef=cfg.vf_coef, ent_coef=cfg.ent_coef),
        clip_value=cfg.clip_value,
        tanh=network.value_scale if network.critic_output == "tanh" else 0.0,
        actions=dist.out_size,
        interpret=interpret,
    )
    if len(devices) == 1:
        return grad
    mesh = Mesh(np.array(devices), ("envs",))
    local = functools.partial(grad, axis=("envs", len(devices)))
    specs = dict(in_specs=(PartitionSpec(), PartitionSpec("envs")), out_specs=PartitionSpec())
    return jax.shard_map(local, mesh=mesh, check_vma=False, **specs)


def _grad(params, batch: Batch, *, loss, clip_value, tanh, actions, interpret, axis=None):
    """The gradient and metrics of one minibatch (`make`); `tanh`: the critic's value scale, 0
    for a linear critic. `axis` (name, size): `batch` is this device's rows of a minibatch split
    over the mesh axis `name` of `size` devices; everything is then over all their rows."""
    from jax.experimental import pallas as pl  # here: only a GPU's learner needs it
    from jax.experimental.pallas import triton as pltriton

    obs, extra = batch.obs
    xc = obs if extra is None else jnp.concatenate([obs, extra], -1)  # [M, D + C]
    here = obs.shape[0]  # this device's rows
    rows = here if axis is None else here * axis[1]  # the minibatch's
    da, dc = _pad(obs.shape[1]), _pad(xc.shape[1])
    actor, critic = _layers(params, "actor"), _layers(params, "critic")
    pa, pc = _padded(actor, da, _pad(actions)), _padded(critic, dc, 16)
    mean, spread = _moments(batch.advantage, axis)
    adv = (batch.advantage - mean) / (spread + 1e-8)  # as ppo_loss: per minibatch
    data = [
        jnp.pad(obs, ((0, 0), (0, da - obs.shape[1]))),
        jnp.pad(xc, ((0, 0), (0, dc - xc.shape[1]))),
        batch.action.astype(jnp.int32),
        batch.log_prob,
        batch.value,
        adv,
        batch.target,
    ]
    weights = [a for layer in pa + pc for a in layer]
    programs = here // ROWS

    def rows_of(x):  # a program's rows of a [M] or [M, D] array
        shape = (ROWS,) + x.shape[1:]
        return pl.BlockSpec(shape, lambda p: (p,) + (0,) * (x.ndim - 1))

    whole = lambda x: pl.BlockSpec(x.shape, lambda p: (0,) * x.ndim)  # noqa: E731
    share = lambda x: pl.BlockSpec(x.shape, lambda p: (p, 0))  # noqa: E731  [I, O] of [P*I, O]
    out_shape = [
        jax.ShapeDtypeStruct((programs * w.shape[0], w.shape[1]), jnp.float32) for w in weights
    ]
    out_shape.append(jax.ShapeDtypeStruct((programs, 8), jnp.float32))
    out_specs = [share(w) for w in weights] + [pl.BlockSpec((1, 8), lambda p: (p, 0))]
    kernel = functools.partial(
        _kernel,
        n_actor=len(pa),
        n_critic=len(pc),
        actions=actions,
        rows=rows,
        clip_value=clip_value,
        tanh=tanh,
        **loss,
    )
    params_ = None if interpret else pltriton.CompilerParams(num_warps=WARPS, num_stages=1)
    *shares, sums = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(programs,),
        in_specs=[rows_of(x) for x in data] + [whole(w) for w in weights],
        out_specs=out_specs,
        interpret=interpret,
        compiler_params=params_,
    )(*data, *weights)
    n = 2 * len(pa)
    grads = _tree(_unpadded(shares[:n], actor), _unpadded(shares[n:], critic))
    grads, sums = _summed((grads, sums.sum(0)), axis)
    return grads, _metrics(sums, rows, loss)


def _moments(x, axis):
    """The mean and standard deviation of `x` [R]: this device's, or with `axis` (name, size)
    of every device's rows (each holding R) in one cross-device op: each device's mean and sum
    of squared deviations, gathered and joined (Chan et al.'s pairwise update)."""
    mean = jnp.mean(x)
    if axis is None:
        return mean, jnp.std(x)
    local = jnp.stack([mean, jnp.square(x - mean).sum()])
    means, squares = lax.all_gather(local, axis[0]).T  # [size] each
    total = jnp.mean(means)
    squared = squares.sum() + x.shape[0] * jnp.square(means - total).sum()
    return total, jnp.sqrt(squared / (x.shape[0] * axis[1]))


def _summed(tree, axis):
    """`tree` summed over the devices of `axis` (None: this device's), its leaves joined into
    one vector first: one cross-device op rather than one a leaf."""
    if axis is None:
        return tree
    flat, unflatten = jax.flatten_util.ravel_pytree(tree)
    return unflatten(lax.psum(flat, axis[0]))


def _metrics(sums, rows: int, loss: dict) -> dict:
    """`ppo_loss`'s metrics from the sums [8] (`SUMS` order) over `rows` transitions."""
    s = dict(zip(SUMS, sums[: len(SUMS)] / rows, strict=True))
    policy_loss, value_loss = -s["surrogate"], 0.5 * s["value_err"]
    return {
        "total": policy_loss + loss["vf_coef"] * value_loss - loss["ent_coef"] * s["entropy"],
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": s["entropy"],
        "approx_kl": s["approx_kl"],
        "clip_fraction": s["clipped"],
    }
