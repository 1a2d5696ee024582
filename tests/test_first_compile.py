"""A run's programs compile at once, each as soon as it is traced (`training.find_programs`), and
a repeated run reads them from the program store (`jaxnav.programs`): the same run, bit for bit,
as compiling one after the other, and nothing is compiled twice."""

import dataclasses
import re

import jax
import numpy as np
import pytest
from conftest import TINY_FLAGS, benchmark_script

import jaxnav.cli.train as train_cli
from jaxnav import programs
from jaxnav import training as train_module
from jaxnav.core import xla
from jaxnav.io import checkpoint, runlog
from jaxnav.ppo import train as ppo_train
from jaxnav.tasks import registry

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"  # an XLA compile or a cache load
TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"  # a trace, named by its function
FIND = train_module.find_programs


def tiny_config(*flags):
    flags = train_cli.parse_args([*TINY_FLAGS, *flags])  # 6 updates in chunks of 2
    return train_module.build_config("cpu", 0, None, train_cli.overrides_from_args(flags))


def trained(out, monkeypatch, ahead: bool, store=None, flags=()) -> tuple[dict, list[dict], dict]:
    """(final train state, metrics rows without timings, {event: [program names]} of the
    traces and compiles) of a tiny run with `flags`, its programs compiled at once (`ahead`) or
    each at its first call, kept in the program store folder `store` (None: the store off)."""
    used = []

    def find_programs(trainer, config, env, key, check=None):
        found = FIND(trainer, config, env, key, ahead=ahead, check=check)
        used.append(found[2])
        return found

    events = {COMPILE_EVENT: [], TRACE_EVENT: []}

    def listen(event, seconds, **kwargs):
        if event in events:
            events[event].append(kwargs.get("fun_name", ""))

    monkeypatch.setattr(train_module, "find_programs", find_programs)
    # As outside the tests, whose XLA_FLAGS set LLVM's level: the programs take jaxnav's options,
    # here at the session's level (-O0), so that these eight tiny runs compile as quickly as the
    # rest of the suite's programs.
    options = lambda *args: {xla.OPTION: 0}  # noqa: E731
    monkeypatch.setattr(ppo_train, "compiler_options", options)
    monkeypatch.setattr(programs, "compiler_options", options)
    programs.use(store)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        final = train_module.run(tiny_config(*flags), out, progress=False)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
        programs.use(None)
    assert used == [ahead]
    with np.load(final / "train_state.npz") as data:
        state = {k: data[k] for k in data.files}
    timing = ("steps_per_second", "elapsed_s")
    rows = [
        {k: v for k, v in row.items() if k not in timing}
        for row in runlog.read_rows(out / "metrics.csv")
    ]
    return state, rows, events


def same_run(got, want) -> None:
    (state, rows, _), (want_state, want_rows, _) = got, want
    assert state.keys() == want_state.keys()
    for key in want_state:  # weights, optimiser, normaliser, robots and RNG: bit for bit
        np.testing.assert_array_equal(state[key], want_state[key], err_msg=key)
    np.testing.assert_equal(rows, want_rows)  # NaN (no episode ended) equals NaN
    assert [r["update"] for r in rows] == [1, 2, 3, 4, 5, 6]


@pytest.mark.slow
@pytest.mark.parametrize(
    "flags, names, stored",
    [
        (
            ("--reset-ahead", "false"),
            {"init": "init", "rollout": "_rollout", "learn": "_learn"},
            False,
        ),
        ((), {"draws": "_draws", "start": "start", "rollout": "_rollout", "learn": "_learn"}, True),
    ],
)
def test_programs_compiled_at_once_train_the_same_and_compile_once(
    tmp_path, monkeypatch, capsys, flags, names, stored
):
    """Slow: tiny training runs in this process, tracing and compiling the trainer. Compiled at
    once, and (`stored`: the default's programs) from the program store (traced and kept by the
    first run, read back by the second: no trace of the task's programs), the run is the one
    whose programs compiled at their first calls, bit for bit. Compiled ahead, the compile line
    also says when the chunk's run began. The programs (`names`: program -> its function's name)
    are init, the rollout and the learner, or, with new episodes drawn ahead (the default), the
    draws, start, rollout and learner; the store keeps programs whatever their names."""
    want = trained(tmp_path / "after", monkeypatch, ahead=False, flags=flags)
    line = re.search(r"first chunk in ([\d.]+) s(.*)", capsys.readouterr().out)
    assert line and line.group(2) == "", line  # compiled at its first call: no split to show
    got = trained(tmp_path / "beside", monkeypatch, ahead=True, flags=flags)
    line = re.search(
        r"first chunk in ([\d.]+) s \(compiled in ([\d.]+) s\)$", capsys.readouterr().out, re.M
    )
    assert line and 0 < float(line.group(2)) <= float(line.group(1)), line
    same_run(got, want)
    # One compile of each program, whose calls run the compiled program.
    for traced in names.values():
        assert sum(f"({traced})" in name for name in got[2][COMPILE_EVENT]) == 1, got[2]
    assert checkpoint.resolve(tmp_path / "beside").name == "update_000006"
    if not stored:
        return
    store = tmp_path / "programs"
    for run in ("traced", "read back"):
        got = trained(tmp_path / run, monkeypatch, ahead=True, store=store, flags=flags)
        same_run(got, want)
        compiled, traced = got[2][COMPILE_EVENT], got[2][TRACE_EVENT]
        for name in names:  # exported under their trace's name
            assert sum(f"(stored_{name})" in n for n in compiled) == 1, compiled
            assert traced.count(name) == (1 if run == "traced" else 0), traced
    programs_kept = sorted(p.name.split("-")[1] for p in store.iterdir())
    assert programs_kept == sorted(f"{name}.program" for name in names)


def test_each_program_compiles_while_the_next_is_traced(monkeypatch):
    """`find_programs` starts a program's compile as soon as it has its abstract arguments and the
    check of init's state (the memory check) has passed, before it traces the programs after it
    (which take its outputs), and the trainer it returns calls the compiled programs. A check that
    fails stops it before anything compiles; with `ahead=False` nothing compiles before the first
    call."""
    import jax.numpy as jnp

    log = []

    class Compiled(train_module._CompiledAhead):
        def __init__(self, program, args):
            log.append(("compile", program.__name__))
            super().__init__(program, args)

    def arguments(name, found, key):
        log.append(("trace", name))
        if name == "double":
            return (key,)
        half = jax.eval_shape(found["double"], key)
        return half if name == "state" else (half,)  # "add"

    def check(state):
        log.append(("check", state.shape))

    double, add = jax.jit(lambda k: 2 * k), jax.jit(lambda x: x + 1)
    double.__name__, add.__name__ = "double", "add"
    compose = lambda p: (lambda k: p["add"](p["double"](k)), None)  # noqa: E731
    trainer = ppo_train.Trainer(None, None, None, None, {}, {}, compose, arguments, ("double",))
    trainer = trainer.with_programs(double=double, add=add)
    monkeypatch.setattr(train_module, "_CompiledAhead", Compiled)
    key = jnp.arange(3.0)
    got, state, ahead = train_module.find_programs(trainer, None, None, key, check=check)
    assert ahead and log == [
        ("trace", "double"),
        ("trace", "state"),
        ("check", (3,)),
        ("compile", "double"),
        ("trace", "add"),
        ("compile", "add"),
    ]
    assert all(isinstance(p, Compiled) for p in got.programs.values())
    np.testing.assert_array_equal(got.init(key), 2 * key + 1)
    assert state.shape == (3,)

    def refuse(state):
        raise ValueError("--num-envs: too many")

    log.clear()
    with pytest.raises(ValueError, match="too many"):
        train_module.find_programs(trainer, None, None, key, check=refuse)
    assert not [entry for entry in log if entry[0] == "compile"]
    log.clear()
    got, _, ahead = train_module.find_programs(trainer, None, None, key, ahead=False)
    assert not ahead and ("compile", "double") not in log and got.programs["add"] is add


def test_programs_compile_with_jaxnav_options(monkeypatch):
    """jaxnav's programs take `core.xla`'s options: LLVM at -O2 on the CPU, deterministic ops on
    a GPU where the config asks, and there no autotuning for the programs that run once a
    rollout or a run (the draws, start, init); other backends, and a user's own setting in
    XLA_FLAGS, keep XLA's defaults."""
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setattr(xla, "_deterministic", False)
    monkeypatch.setattr(xla, "_fusion_autotune", True)  # as the goal task's trainers leave it
    untuned = {xla.AUTOTUNE: 0}
    assert xla.compiler_options("cpu") == {xla.OPTION: xla.CPU_OPT_LEVEL}
    assert xla.compiler_options("cpu", "rollout") == {xla.OPTION: xla.CPU_OPT_LEVEL}
    for name in (None, "rollout", "learn"):
        assert xla.compiler_options("gpu", name) is None
    assert set(xla.UNTUNED) == {"draws", "start", "init"}
    for name in xla.UNTUNED:
        assert xla.compiler_options("gpu", name) == untuned
    xla.deterministic(True)
    for gpu in ("gpu", "cuda", "rocm"):
        assert xla.compiler_options(gpu) == {xla.DETERMINISTIC: True}
        assert xla.compiler_options(gpu, "draws") == {xla.DETERMINISTIC: True, **untuned}
    assert xla.compiler_options("tpu") is None and xla.compiler_options("tpu", "draws") is None
    monkeypatch.setenv("XLA_FLAGS", f"--{xla.OPTION}=3 --{xla.AUTOTUNE}=4")
    assert xla.compiler_options("cpu") is None
    assert xla.compiler_options("gpu", "start") == {xla.DETERMINISTIC: True}
    monkeypatch.setenv("XLA_FLAGS", f"--{xla.DETERMINISTIC}=false")
    assert xla.compiler_options("gpu") is None
    assert xla.compiler_options("gpu", "init") == untuned


def test_the_trainer_hands_its_options_to_xla(monkeypatch):
    """The options reach XLA's compile of the trainer's programs: an option XLA does not know
    fails the compile, naming it."""
    monkeypatch.setattr(ppo_train, "compiler_options", lambda *args: {"xla_no_such_one": 1})
    config = tiny_config()
    trainer = ppo_train.make_train(config.ppo, train_module.make_run_env(config))
    with pytest.raises(Exception, match="xla_no_such_one"):
        trainer.init(jax.random.PRNGKey(0))


def _lowered_for_cuda(env) -> str:
    """The StableHLO of `env`'s reset over 8 robots, exported for CUDA (as a GPU lowers it)."""
    import jax.numpy as jnp
    from jax import export

    keys = jax.ShapeDtypeStruct((8, 2), jnp.uint32)
    return export.export(jax.jit(jax.vmap(env.reset)), platforms=["cuda"])(keys).mlir_module()


@pytest.mark.slow
def test_the_threefry_kernel_is_an_option_handed_to_the_lowering(monkeypatch):
    """No preset sets `threefry_kernel`; `make_train` hands the setting on;
    `core.xla.threefry_kernel` sets JAX's lowering on a GPU only: lowered for CUDA, the goal
    reset then calls JAX's threefry kernel where it inlined the rounds. Slow: about 7 s on 2
    cores, the goal task's trainer built and its reset lowered twice."""
    import jaxnav

    build = train_module.build_config
    assert not build("gpu", env="goal").ppo.threefry_kernel
    assert not build("gpu", env="avoid").ppo.threefry_kernel
    calls = []
    monkeypatch.setattr(ppo_train, "threefry_kernel", lambda *args: calls.append(args))
    config = build("cpu", env="goal", overrides={"ppo": {"threefry_kernel": True}})
    ppo_train.make_train(config.ppo, train_module.make_run_env(config))
    assert calls == [(True, jax.devices()[0].platform)]  # the platform it trains on
    before = jax.config.values[xla.THREEFRY_KERNEL]
    env = jaxnav.make_env("goal")
    lowered = {}
    try:
        for on in (False, True):
            xla.threefry_kernel(not on, "gpu")
            xla.threefry_kernel(on, "cpu")  # no such kernel there: the setting stays
            assert jax.config.values[xla.THREEFRY_KERNEL] is (not on)
            xla.threefry_kernel(on, "gpu")
            assert jax.config.values[xla.THREEFRY_KERNEL] is on
            lowered[on] = _lowered_for_cuda(env)
    finally:
        jax.config.update(xla.THREEFRY_KERNEL, before)
    assert "threefry2x32_ffi" not in lowered[False] and "threefry2x32_ffi" in lowered[True]


@pytest.mark.slow
def test_programs_run_once_a_rollout_lower_with_the_threefry_kernel(tmp_path, monkeypatch):
    """`xla.LoweredWith` lowers its program, and `jaxnav.programs` exports it, in its context
    (`xla.run_once`, on one GPU only: `make_train`'s draws, start and init with the threefry
    kernel), and only while it lowers; lowered for CUDA in it, a reset calls the kernel; traced
    inside another program, it gives its shapes. `make_train` wraps its draws and start on one GPU
    only. Slow: about 9 s on 2 cores, a trainer built and a reset lowered for CUDA."""
    from jax._src.config import threefry_gpu_kernel_lowering as state

    import jaxnav

    class Fake:  # a jitted program that says how it was lowered or called
        def lower(self, *args):
            return state.value

        __call__ = lower

    kernel = lambda: xla.threefry_lowering(True)  # noqa: E731
    program = xla.LoweredWith(Fake(), kernel)
    assert program.lower() is True and program() is True and Fake().lower() is False
    seen = []
    export = programs._export
    monkeypatch.setattr(programs, "_export", lambda *a: seen.append(state.value) or export(*a))
    trainer = ppo_train.Trainer(
        None, None, None, None, parts={"draws": lambda x: 2 * x, "start": lambda x: x + 1}
    )
    trainer = trainer._replace(
        programs={"draws": xla.LoweredWith(jax.jit(lambda x: 2 * x), kernel), "start": None}
    )
    programs.use(tmp_path)
    try:
        x = np.arange(3.0, dtype=np.float32)
        stored = {n: programs.program(trainer, "run", n, (x,)) for n in ("draws", "start")}
    finally:
        programs.use(None)
    assert seen == [True, False] and state.value is False
    np.testing.assert_array_equal(stored["draws"](x), 2 * x)
    env = jaxnav.make_env("goal")
    with xla.lowering(program):
        assert "threefry2x32_ffi" in _lowered_for_cuda(env)
    assert "threefry2x32_ffi" not in _lowered_for_cuda(env)
    config = tiny_config()
    env = train_module.make_run_env(config)
    monkeypatch.setenv("XLA_FLAGS", "")  # each program jitted with jaxnav's options
    trainer = ppo_train.make_train(config.ppo, env)
    one_gpu = jax.default_backend() in xla.GPUS and jax.device_count() == 1
    wrapped = {n for n, p in trainer.programs.items() if isinstance(p, xla.LoweredWith)}
    assert wrapped == ({"draws", "start"} if one_gpu else set()), wrapped
    # Wrapped as on one GPU, with the program store off, a run still traces each program on the
    # shapes of those before it (`Trainer.arguments`: `jax.eval_shape` of a jit with options).
    jitted = {n: getattr(trainer.programs[n], "jitted", trainer.programs[n]) for n in wrapped}
    trainer = trainer.with_programs(**jitted)  # as on the CPU
    once = xla.run_once({n: trainer.programs[n] for n in ("draws", "start")}, "gpu", 1)
    key = jax.random.PRNGKey(0)
    found, ts, _ = FIND(trainer.with_programs(**once), config, env, key, ahead=False)
    assert isinstance(found.programs["draws"], xla.LoweredWith)
    want = trainer.arguments("state", trainer.programs, key)
    assert jax.tree_util.tree_leaves(ts) == jax.tree_util.tree_leaves(want)
    once = {"draws": Fake(), "start": Fake()}
    for platform, devices in (("cpu", 1), ("gpu", 2), ("tpu", 1)):
        assert xla.run_once(once, platform, devices) is once
    for gpu in ("gpu", "cuda"):
        wrapped = xla.run_once(once, gpu, 1)
        assert set(wrapped) == set(once) and all(p.lower() is True for p in wrapped.values())


@pytest.mark.parametrize("task, most", [("avoid", 6), ("goal", 8)])
def test_a_reset_lowered_for_a_gpu_holds_few_hashes(task, most):
    """Lowered for CUDA with threefry inlined (JAX's default), a reset holds a handful of threefry
    hashes: its dozens of values (room, spawn, robot, goal) come from `Draws` blocks. With a key
    per value it held 23 (avoid) and 37 (goal), each ~130 unrolled ops."""
    import jaxnav

    before = jax.config.values[xla.THREEFRY_KERNEL]
    try:
        xla.threefry_kernel(False, "gpu")
        text = _lowered_for_cuda(jaxnav.make_env(task))
    finally:
        jax.config.update(xla.THREEFRY_KERNEL, before)
    hashes = text.count("call @threefry2x32")
    assert 0 < hashes <= most, hashes


def test_the_config_turns_the_fusion_autotuner_off(monkeypatch):
    """`PPOConfig.fusion_autotune` off has every GPU program compiled without XLA timing its
    fusions' kernels, as `make_train` builds the trainer, and back on; a user's own setting in
    XLA_FLAGS is kept; the CPU's options are as they were; the goal task turns it off, `avoid`
    keeps XLA's default."""
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setattr(xla, "_deterministic", False)
    monkeypatch.setattr(xla, "_fusion_autotune", True)
    config = tiny_config()
    env = train_module.make_run_env(config)
    ppo_train.make_train(dataclasses.replace(config.ppo, fusion_autotune=False), env)
    off = {xla.FUSION_AUTOTUNE: False}
    assert xla.compiler_options("gpu") == off and xla.compiler_options("gpu", "learn") == off
    assert xla.compiler_options("gpu", "draws") == {**off, xla.AUTOTUNE: 0}
    assert xla.compiler_options("cpu") == {xla.OPTION: xla.CPU_OPT_LEVEL}
    monkeypatch.setenv("XLA_FLAGS", f"--{xla.FUSION_AUTOTUNE}=true")
    assert xla.compiler_options("gpu") is None
    monkeypatch.delenv("XLA_FLAGS")
    ppo_train.make_train(config.ppo, env)
    assert xla.compiler_options("gpu") is None
    assert not registry.task_defaults("goal")["ppo"]["fusion_autotune"]
    assert "fusion_autotune" not in registry.task_defaults("avoid").get("ppo", {})
    # XLA knows the option (an unknown one fails the compile: the test below).
    assert jax.jit(lambda x: x + 1, compiler_options=off)(1) == 2


def test_the_config_asks_for_deterministic_ops(monkeypatch):
    """`PPOConfig.deterministic` sets the process's GPU option as `make_train` builds the trainer,
    on and back off."""
    monkeypatch.setattr(xla, "_deterministic", False)
    monkeypatch.setattr(xla, "_fusion_autotune", True)
    config = tiny_config()
    env = train_module.make_run_env(config)
    ppo_train.make_train(dataclasses.replace(config.ppo, deterministic=True), env)
    assert xla.compiler_options("gpu") == {xla.DETERMINISTIC: True}
    ppo_train.make_train(config.ppo, env)
    assert xla.compiler_options("gpu") is None


def test_the_compile_log_names_each_programs_slowest_passes():
    """`benchmarks/compile_time.py --xla-log` sums each HLO pass of XLA's log into the module
    whose pipeline it started in: an autotuning pass's time comes after the modules it compiled
    inside it, and still counts for its own module; units as XLA prints them."""
    compile_time = benchmark_script("compile_time")
    log = """\
I1201 06:07:17.1 495 hlo_pass_pipeline.cc:302] Running HLO pass pipeline on module jit__draws: fusion
I1201 06:07:17.2 495 hlo_pass_pipeline.cc:211]   HLO pass priority-fusion
I1201 06:07:20.7 495 hlo_pass_pipeline.cc:206] HLO pass: priority-fusion time: 3.49 s (3490000 us)
I1201 06:07:20.8 495 hlo_pass_pipeline.cc:211]   HLO pass config-assigner
I1201 06:07:20.9 495 hlo_pass_pipeline.cc:302] Running HLO pass pipeline on module fusion_7: opt
I1201 06:07:20.9 495 hlo_pass_pipeline.cc:211]   HLO pass algsimp
I1201 06:07:20.9 495 hlo_pass_pipeline.cc:206] HLO pass: algsimp time: 250 us (250 us)
I1201 06:07:21.8 495 hlo_pass_pipeline.cc:206] HLO pass: config-assigner time: 1.04 s (1040000 us)
I1201 06:07:21.9 495 hlo_pass_pipeline.cc:302] Running HLO pass pipeline on module jit__learn: x
I1201 06:07:21.9 495 hlo_pass_pipeline.cc:211]   HLO pass algsimp
I1201 06:07:21.9 495 hlo_pass_pipeline.cc:206] HLO pass: algsimp time: 20 ms (20000 us)
I1201 06:07:21.9 495 hlo_pass_pipeline.cc:211]   HLO pass algsimp
I1201 06:07:21.9 495 hlo_pass_pipeline.cc:206] HLO pass: algsimp time: 30 ms (30000 us)
"""
    assert compile_time.pass_seconds(log) == {
        "jit__draws": {"priority-fusion": 3.49, "config-assigner": 1.04},
        "fusion_7": {"algsimp": 0.0},
        "jit__learn": {"algsimp": 0.05},
    }
    assert compile_time.pass_seconds(log, top=1)["jit__draws"] == {"priority-fusion": 3.49}
