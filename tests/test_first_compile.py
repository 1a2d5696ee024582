"""A run's first chunk compiles beside `init` (`training.compile_chunk_ahead`): the same run, bit
for bit, as compiling one after the other, and nothing is compiled twice."""

import jax
import numpy as np
import pytest
from conftest import TINY_FLAGS

import jaxnav.cli.train as train_cli
from jaxnav import training as train_module
from jaxnav.core import xla
from jaxnav.io import checkpoint, runlog
from jaxnav.ppo import train as ppo_train

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"  # an XLA compile or a cache load
CHUNK_AHEAD = train_module.compile_chunk_ahead


def tiny_config():
    flags = train_cli.parse_args(TINY_FLAGS)  # 6 updates in chunks of 2
    return train_module.build_config("cpu", 0, None, train_cli.overrides_from_args(flags))


def trained(out, monkeypatch, ahead: bool) -> tuple[dict, list[dict], list[str]]:
    """(final train state, metrics rows without timings, the programs compiled) of a tiny run,
    its chunk compiled beside init (`ahead`) or after it."""
    used = []

    def chunk_ahead(trainer, key):
        trainer, compiling = CHUNK_AHEAD(trainer, key) if ahead else (trainer, None)
        used.append(compiling is not None)
        return trainer, compiling

    compiled = []

    def listen(event, seconds, **kwargs):
        if event == COMPILE_EVENT:
            compiled.append(kwargs.get("fun_name", ""))

    monkeypatch.setattr(train_module, "compile_chunk_ahead", chunk_ahead)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        final = train_module.run(tiny_config(), out, progress=False)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert used == [ahead]
    with np.load(final / "train_state.npz") as data:
        state = {k: data[k] for k in data.files}
    timing = ("steps_per_second", "elapsed_s")
    rows = [
        {k: v for k, v in row.items() if k not in timing}
        for row in runlog.read_rows(out / "metrics.csv")
    ]
    return state, rows, compiled


@pytest.mark.slow
def test_chunk_compiled_beside_init_trains_the_same_and_compiles_once(tmp_path, monkeypatch):
    """Slow: two tiny training runs in this process, each tracing and compiling the trainer."""
    want_state, want_rows, _ = trained(tmp_path / "after", monkeypatch, ahead=False)
    state, rows, compiled = trained(tmp_path / "beside", monkeypatch, ahead=True)
    assert state.keys() == want_state.keys()
    for key in want_state:  # weights, optimiser, normaliser, robots and RNG: bit for bit
        np.testing.assert_array_equal(state[key], want_state[key], err_msg=key)
    np.testing.assert_equal(rows, want_rows)  # NaN (no episode ended) equals NaN
    assert [r["update"] for r in rows] == [1, 2, 3, 4, 5, 6]
    # One compile each of init and of the chunk, whose three calls run the compiled program.
    assert sum("(run_chunk)" in name for name in compiled) == 1, compiled
    assert sum("(init)" in name for name in compiled) == 1, compiled
    assert checkpoint.resolve(tmp_path / "beside").name == "update_000006"


def test_cpu_programs_compile_at_jaxnav_level(monkeypatch):
    """On the CPU, jaxnav's programs take `core.xla`'s options (LLVM at -O2); other backends and a
    user's own level in XLA_FLAGS keep XLA's defaults."""
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert xla.compiler_options("cpu") == {xla.OPTION: xla.CPU_OPT_LEVEL}
    assert xla.compiler_options("cuda") is None
    monkeypatch.setenv("XLA_FLAGS", f"--{xla.OPTION}=3")
    assert xla.compiler_options("cpu") is None


def test_the_trainer_hands_its_options_to_xla(monkeypatch):
    """The options reach XLA's compile of the trainer's programs: an option XLA does not know
    fails the compile, naming it."""
    monkeypatch.setattr(ppo_train, "compiler_options", lambda platform: {"xla_no_such_one": 1})
    config = tiny_config()
    trainer = ppo_train.make_train(config.ppo, train_module.make_run_env(config))
    with pytest.raises(Exception, match="xla_no_such_one"):
        trainer.init(jax.random.PRNGKey(0))
