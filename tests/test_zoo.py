"""rl-zoo3 launcher and configs: train, enjoy and -optimize through rl-zoo3's own entry points."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

import envs
from sb3_taskalloc import SelectDAggerCallback, TAMPolicy, TwoStageSAC
from sb3_taskalloc.two_stage_sac.dagger import teacher_costs
from sb3_taskalloc.two_stage_sac.settings import RECOMMENDED_DECODERS
from sb3_taskalloc.zoo_config import zoo_dagger, zoo_hyperparameters

pytest.importorskip("rl_zoo3", reason='rl-zoo3 is the optional "zoo" extra')

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "zoo_configs"


def zoo(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    # This checkout goes ahead of any PYTHONPATH the test process has, which stays: it may hold the dependencies.
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path}
    proc = subprocess.run(
        [sys.executable, "-m", "sb3_taskalloc.zoo", *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def test_importing_the_package_does_not_import_rl_zoo3():
    code = "import sys, sb3_taskalloc, sb3_taskalloc.zoo; assert 'rl_zoo3' not in sys.modules, 'rl_zoo3 imported'"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


@pytest.mark.parametrize("name", ["two_stage_sac.yml", "maskable_ppo.yml"])
def test_configs_have_a_valid_block_per_env(name):
    config = yaml.safe_load((CONFIGS / name).read_text())
    assert set(envs.ENV_SPECS) <= set(config), set(envs.ENV_SPECS) - set(config)
    if name != "two_stage_sac.yml":
        return
    algo_args = set(inspect.signature(TwoStageSAC.__init__).parameters)
    policy_args = set(inspect.signature(TAMPolicy.__init__).parameters)
    for env_id in envs.ENV_SPECS:
        block = dict(config[env_id])
        assert block.pop("policy") == "TAMPolicy" and block.pop("n_timesteps") > 0
        assert block.pop("n_envs", 1) >= 1  # rl-zoo3's key: the VecEnv, not a TwoStageSAC keyword
        if block.pop("callback", None) is not None:  # rl-zoo3's key: only the DAgger callback, which the experiments run
            teacher_costs(zoo_dagger(env_id, CONFIGS / name).get("teacher"), env_id)  # as the callback does at learn()
        assert set(block) <= algo_args, set(block) - algo_args
        assert set(block.get("policy_kwargs", {})) <= policy_args
        TwoStageSAC("TAMPolicy", env_id, **block, _init_setup_model=False)  # every setting passes the constructor's checks
    # `default` lists only what differs from the constructor defaults.
    defaults = {k: p.default for k, p in inspect.signature(TwoStageSAC.__init__).parameters.items()}
    assert not {k: v for k, v in config["default"].items() if defaults.get(k, object()) == v}
    block = {k: v for k, v in config["TaskAlloc/Almighty-v0"].items() if k not in ("policy", "n_timesteps", "n_envs")}
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", **block)
    assert model.learning_rate == pytest.approx(1e-3) and model.policy.hidden_dim == 64


def test_zoo_config_names_the_dagger_callback():
    """The ``callback`` entry that :class:`SelectDAggerCallback`'s docstring gives builds it through rl-zoo3."""
    from rl_zoo3.utils import get_callback_list

    entry = yaml.safe_load(SelectDAggerCallback.__doc__.split("::")[1].split("The rollouts")[0])  # type: ignore[union-attr]
    (callback,) = get_callback_list(entry)
    assert isinstance(callback, SelectDAggerCallback)
    assert callback.kwargs["iterations"] == 8 and callback.kwargs["imitation"] == "set"


def test_zoo_train_then_enjoy(tmp_path):
    zoo(
        tmp_path, "train", "--algo", "two_stage_sac", "--env", "TaskAlloc/Almighty-v0",
        "--conf-file", str(CONFIGS / "two_stage_sac.yml"), "-n", "100", "--eval-freq", "-1", "--seed", "0", "-f", "logs",
        "-params", "learning_starts:40", "batch_size:16",
    )  # fmt: skip
    path = tmp_path / "logs/two_stage_sac/TaskAlloc-Almighty-v0_1/TaskAlloc-Almighty-v0.zip"
    assert path.exists()
    model = TwoStageSAC.load(path, buffer_size=1)
    assert model.num_timesteps == 100 and model._n_updates == 60 and model.batch_size == 16
    out = zoo(
        tmp_path, "enjoy", "--algo", "two_stage_sac", "--env", "TaskAlloc/Almighty-v0", "-f", "logs", "--exp-id", "1",
        "-n", "3", "--no-render", "--deterministic",
    ).stdout  # fmt: skip
    assert "Mean reward" in out and "Episode Reward" in out


def test_zoo_optimize_two_trials(tmp_path):
    out = zoo(
        tmp_path, "train", "--algo", "two_stage_sac", "--env", "TaskAlloc/Almighty-v0",
        "--conf-file", str(CONFIGS / "two_stage_sac.yml"), "-n", "60", "-optimize", "--n-trials", "2",
        "--n-evaluations", "2", "--eval-episodes", "1", "--n-startup-trials", "1", "--seed", "0", "-f", "logs",
    ).stdout  # fmt: skip
    assert "Number of finished trials:  2" in out
    reports = list((tmp_path / "logs/two_stage_sac").glob("report_*.csv"))
    assert len(reports) == 1 and len(reports[0].read_text().strip().splitlines()) == 3  # header + 2 trials


def test_zoo_usage_error():
    proc = subprocess.run([sys.executable, "-m", "sb3_taskalloc.zoo", "fly"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode != 0 and "usage" in proc.stderr


def block_policy_kwargs(env_id: str) -> dict:
    """The ``policy_kwargs`` of ``env_id``'s block in the shipped config, read as every experiment reads it."""
    return zoo_hyperparameters(env_id, CONFIGS / "two_stage_sac.yml")["policy_kwargs"]


def test_rbf_block_prices_the_pointer_with_the_recommended_values():
    """RBF's pointer decodes on the recommended decoder's costs: the block's θ is ``entity_value``'s. RBF-TaskShift
    trains with RBF's whole policy block, and RBF-EntityShift keeps the observation's costs (RBF's θ measured better
    on the one and no better on the other: results/learn_shifted_seeds20)."""
    name, decoder = RECOMMENDED_DECODERS["TaskAlloc/RBF-v0"]
    assert name == "entity_value"
    block = block_policy_kwargs("TaskAlloc/RBF-v0")
    assert tuple(block["select_values"]["theta"]) == tuple(decoder["theta"])
    assert block_policy_kwargs("TaskAlloc/RBF-TaskShift-v0") == block
    assert block_policy_kwargs("TaskAlloc/RBF-EntityShift-v0") == {"rounds": block["rounds"]}


def test_mt_block_prices_the_pointer_with_the_recommended_surcharge():
    """MT's pointer decodes on the recommended decoder's costs, (1 + σ)·c_ij with its σ, and the shifted MT envs train
    with MT's whole policy block (measured on them: results/learn_shifted_seeds20)."""
    name, decoder = RECOMMENDED_DECODERS["TaskAlloc/MT-v0"]
    assert name == "exact_top"
    block = block_policy_kwargs("TaskAlloc/MT-v0")
    assert block["select_values"] == {"surcharge": decoder["surcharge"]}
    for shifted in ("TaskAlloc/MT-EntityShift-v0", "TaskAlloc/MT-TaskShift-v0"):
        assert block_policy_kwargs(shifted) == block


def test_zoo_train_uses_the_shipped_config_by_default(monkeypatch):
    """``python -m sb3_taskalloc.zoo train`` without ``--conf-file`` trains with the packaged config, not rl-zoo3's
    folder (which knows no TaskAlloc id)."""
    import sys

    import rl_zoo3.train

    from sb3_taskalloc import zoo
    from sb3_taskalloc.zoo_config import config_path

    seen: list[list[str]] = []
    monkeypatch.setattr(rl_zoo3.train, "train", lambda: seen.append(list(sys.argv)))
    monkeypatch.setattr(sys, "argv", ["x"])
    zoo.main(["train", "--algo", "two_stage_sac", "--env", "TaskAlloc/RBF-v0"])
    assert seen[0][seen[0].index("--conf-file") + 1] == str(config_path("two_stage_sac.yml"))
    assert config_path("two_stage_sac.yml").is_file() and config_path("ddpg.yml").is_file()


def test_zoo_train_names_a_block_rl_zoo3_cannot_train(tmp_path, monkeypatch):
    """A block without ``policy`` or ``n_timesteps`` ended in rl-zoo3's bare ``KeyError: 'n_timesteps'``; bad YAML in a
    traceback. Both are named before rl-zoo3 starts; ``-n`` stands in for ``n_timesteps``."""
    import sys

    import rl_zoo3.train

    from sb3_taskalloc import zoo

    seen: list[list[str]] = []
    monkeypatch.setattr(rl_zoo3.train, "train", lambda: seen.append(list(sys.argv)))
    monkeypatch.setattr(sys, "argv", ["x"])
    conf = tmp_path / "c.yml"
    base = ["train", "--algo", "two_stage_sac", "--env", "TaskAlloc/Almighty-v0", "--conf-file", str(conf)]
    for text, match in [
        ("TaskAlloc/Almighty-v0:\n  learning_rate: 0.001\n", "has no policy or n_timesteps, which rl-zoo3 needs"),
        ("TaskAlloc/Almighty-v0:\n  policy: TAMPolicy\n", "has no n_timesteps"),
        ("TaskAlloc/Almighty-v0: [1, 2\n", r"(?s)c\.yml is not valid YAML.*c\.yml\", line 2"),
    ]:
        conf.write_text(text)
        with pytest.raises(SystemExit, match=match):
            zoo.main(base)
    assert not seen
    conf.write_text("TaskAlloc/Almighty-v0:\n  policy: TAMPolicy\n")
    zoo.main([*base, "-n", "100"])
    assert len(seen) == 1
