"""``--plugin MODULE`` (pcdet_atlas.utils.cli.import_plugins): a user module written to a temporary
folder registers a detector, a model stage and an attack family, and tools/train.py,
tools/test.py, tools/evaluate_predictions.py and tools/report.py use them; a module that is not
there or registers nothing is one clear error."""

from __future__ import annotations

import sys
import textwrap

import pytest

import pcdet_atlas.evaluation.analyses  # noqa: F401 - imported before a test snapshots sys.modules
from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.registry import ATTACKS, DETECTORS, REGISTRIES, RegistryError
from pcdet_atlas.utils.cli import PluginError, import_plugins
from pcdet_atlas.utils.common import load_tool

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"

PLUGIN = '''
"""A user's plugin: one detector, one model stage, one attack family."""
from pcdet_atlas.attacks.removal import RemovalAttack
from pcdet_atlas.models.detectors.centerpoint import CenterPoint
from pcdet_atlas.models.vfe.dynamic_pillar_vfe import DynamicPillarVFE
from pcdet_atlas.registry import ATTACKS, DETECTORS, MODEL_STAGES

CALLS = {"detector": 0, "stage": 0}


@DETECTORS.register()
class PluginCenterPoint(CenterPoint):
    def loss(self, batch_dict):
        CALLS["detector"] += 1
        return super().loss(batch_dict)

    def predict(self, batch_dict):
        CALLS["detector"] += 1
        return super().predict(batch_dict)


@MODEL_STAGES.register()
class PluginPillarVFE(DynamicPillarVFE):
    def forward(self, batch_dict):
        CALLS["stage"] += 1
        return super().forward(batch_dict)


@ATTACKS.register()
class PluginRemoval(RemovalAttack):
    family = "plugin_removal"
'''


@pytest.fixture
def clean_registries():
    """Registries and modules as they were before the test (a plugin registers globally)."""
    for registry in REGISTRIES.values():
        registry.list()  # the built-ins first, so that restoring keeps them
    saved = {kind: dict(registry._items) for kind, registry in REGISTRIES.items()}
    modules = set(sys.modules)
    yield
    for kind, registry in REGISTRIES.items():
        registry._items.clear()
        registry._items.update(saved[kind])
    for name in set(sys.modules) - modules:
        del sys.modules[name]


def write(path, text):
    path.write_text(textwrap.dedent(text))
    return path


def test_a_plugin_file_or_module_registers_one_of_each(clean_registries, tmp_path, monkeypatch):
    plugin = write(tmp_path / "atlas_user_plugin.py", PLUGIN)
    assert "PluginCenterPoint" not in DETECTORS
    added = import_plugins([str(plugin)])
    assert added == {str(plugin): {"attack": ["PluginRemoval"], "detector": ["PluginCenterPoint"],
                                   "model stage": ["PluginPillarVFE"]}}  # fmt: skip
    assert ATTACKS.get("PluginRemoval").family == "plugin_removal"
    assert import_plugins([str(plugin)]) == {str(plugin): {}}  # imported once per process
    # by dotted name, from the Python path
    (tmp_path / "pkg_plugins").mkdir()
    write(tmp_path / "pkg_plugins" / "__init__.py", "")
    write(tmp_path / "pkg_plugins" / "second.py", PLUGIN.replace("Plugin", "Other"))
    monkeypatch.syspath_prepend(str(tmp_path))
    added = import_plugins(["pkg_plugins.second"])
    assert added["pkg_plugins.second"]["detector"] == ["OtherCenterPoint"]


def test_bad_plugins_are_clear_errors(clean_registries, tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(PluginError, match=r"--plugin no_such_plugin: no module named"):
        import_plugins(["no_such_plugin"])
    with pytest.raises(PluginError, match=r"--plugin .*missing\.py: no such file"):
        import_plugins([str(tmp_path / "missing.py")])
    write(tmp_path / "idle_plugin.py", "X = 1\n")
    nothing = r"--plugin idle_plugin: registered nothing in the dataset, transform, attack, "
    with pytest.raises(
        PluginError, match=nothing + "detector, model stage, analysis, confidence kind registries"
    ):
        import_plugins(["idle_plugin"])
    # the plugin's own errors are its own: a missing dependency, a name taken by a built-in
    write(tmp_path / "needy_plugin.py", "import not_installed_dependency\n")
    with pytest.raises(ModuleNotFoundError, match="not_installed_dependency"):
        import_plugins(["needy_plugin"])
    write(tmp_path / "clash_plugin.py", """
        from pcdet_atlas.models.detectors.centerpoint import CenterPoint
        from pcdet_atlas.registry import DETECTORS

        DETECTORS.register("CenterPoint")(type("Mine", (CenterPoint,), {}))
    """)  # fmt: skip
    with pytest.raises(RegistryError, match=r"name 'CenterPoint' is already registered"):
        import_plugins([str(tmp_path / "clash_plugin.py")])


@pytest.mark.slow
def test_tools_train_test_score_and_report_with_a_plugin(
    clean_registries, synthetic_root, tmp_path
):
    plugin = str(write(tmp_path / "atlas_e2e_plugin.py", PLUGIN))
    data = ["DATA_CONFIG.DATA_PATH", str(synthetic_root),
            "DATA_CONFIG.POINT_CLOUD_RANGE", "-20.48,-20.48,-2,20.48,20.48,4"]  # fmt: skip
    model = ["MODEL.NAME", "PluginCenterPoint", "MODEL.VFE.NAME", "PluginPillarVFE"]
    trained = load_tool("train").main([
        "--plugin", plugin, "--cfg", str(CFG), "--out_dir", str(tmp_path / "output"),
        "--epochs", "1", "--batch_size", "2", "--workers", "0", "--no_progress", "--device",
        "cpu", "--set", *data, *model, "DATA_CONFIG.SAMPLED_INTERVAL", "train:10,test:10",
        "DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST", "gt_sampling",
    ])  # fmt: skip
    calls = sys.modules["atlas_e2e_plugin"].CALLS
    assert calls["detector"] >= 1 and calls["stage"] >= 1  # the plugin's classes trained
    ckpt = trained["output_dir"] / "ckpt" / "checkpoint_epoch_1.pth"
    variant = write(tmp_path / "plugin_rem.yaml", f"""
        _BASE_CONFIG_: {REPO_ROOT / "cfgs/attacks/rem_40.yaml"}
        NAME: PluginRemoval
        VARIANT: plugin_rem
    """)  # fmt: skip
    before = dict(calls)
    tested = load_tool("test").main([
        "--plugin", plugin, "--cfg", str(CFG), "--ckpt", str(ckpt), "--attacks",
        f"clean,{variant}", "--out_dir", str(tmp_path / "output"), "--workers", "0",
        "--no_progress", "--device", "cpu", "--set", *data, *model,
        "DATA_CONFIG.SAMPLED_INTERVAL", "train:1,test:14",
    ])  # fmt: skip
    assert calls["detector"] > before["detector"] and calls["stage"] > before["stage"]
    entry = tested["results"]["variants"]["plugin_rem"]
    assert entry["family"] == "plugin_removal" and entry["num_targets"] > 0
    eval_dir = tested["output_dir"]
    scored = load_tool("evaluate_predictions").main([
        "--plugin", plugin, "--data_cfg", str(CFG), "--predictions",
        f"clean={eval_dir / 'clean' / 'result.pkl'}",
        f"{variant}={eval_dir / 'plugin_rem' / 'result.pkl'}", "--out_dir", str(tmp_path / "s"),
        "--set", *data, "DATA_CONFIG.SAMPLED_INTERVAL", "train:1,test:14",
    ])  # fmt: skip
    got = scored["variants"]["plugin_rem"]
    assert got["family"] == "plugin_removal"
    assert (got["num_targets"], got["num_success"]) == (entry["num_targets"], entry["num_success"])
    report = load_tool("report").main(
        ["--plugin", plugin, "--results", str(tmp_path / "s"), "--out_dir", str(tmp_path / "rep")]
    )
    assert "plugin_rem" in report["report"].read_text()


ANALYSIS_PLUGIN = '''
"""A user's plugin: one analysis and one confidence kind."""
from pcdet_atlas.evaluation.analyses import (
    Analysis, ConfidenceKind, register_analysis, register_confidence_kind,
)


@register_analysis
class PluginNothing(Analysis):
    name = "plugin_nothing"

    def schema(self):
        return {}

    def compute(self, data):
        return {}


register_confidence_kind(ConfidenceKind(name="plugin_kind", compute=lambda data: {},
                                        shown="num_detected", properties={}))
'''


def test_a_plugin_registers_an_analysis_and_a_confidence_kind(clean_registries, tmp_path):
    plugin = write(tmp_path / "atlas_analysis_plugin.py", ANALYSIS_PLUGIN)
    added = import_plugins([str(plugin)])
    assert added == {str(plugin): {"analysis": ["plugin_nothing"],
                                   "confidence kind": ["plugin_kind"]}}  # fmt: skip
    assert (
        "plugin_nothing" in REGISTRIES["analysis"]
        and "plugin_kind" in REGISTRIES["confidence kind"]
    )
