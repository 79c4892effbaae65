"""Config sections declared once (pcdet_atlas/config_values.py): a frozen dataclass of
``setting`` fields read by ``read_section``, with errors naming the file, the key path, the value
and what was expected; and the declarations in use agree with the constructors they feed."""

from __future__ import annotations

import inspect
from dataclasses import dataclass

import pytest

from pcdet_atlas.config import ConfigError, cfg_from_yaml_file
from pcdet_atlas.config_values import (
    REQUIRED,
    declared_defaults,
    declared_keys,
    declared_settings,
    is_declaration,
    read_section,
    section,
    setting,
)


@dataclass(frozen=True, kw_only=True)
class Inner:
    dt: float = setting(0.1, gt=0, doc="s per frame")


@dataclass(frozen=True, kw_only=True)
class Outer:
    budget: tuple[int, int] = setting(
        ge=1, check=lambda b: b[0] <= b[1], expected="[lo, hi] with 1 <= lo <= hi"
    )
    p: float = setting(0.01, ge=0, le=1)
    mode: str = setting("a", choices=("a", "b"))
    sizes: tuple[float, ...] = setting((1.0, 2.0), gt=0)
    enabled: bool = setting(False)
    inner: Inner = section(Inner)
    maybe: Inner | None = setting(None)
    count: int | None = setting(None, ge=0)
    width_m: float = setting(2.0, key="WIDTH")

    def __post_init__(self) -> None:
        if self.enabled and self.mode != "b":
            raise ValueError("ENABLED needs MODE b")


def load(tmp_path, text: str):
    path = tmp_path / "sec.yaml"
    path.write_text(text)
    return cfg_from_yaml_file(path)


def test_defaults_conversion_and_nested_sections(tmp_path):
    got = read_section(Outer, load(tmp_path, "BUDGET: [1, 3]\nP: 1\nINNER:\n  DT: 2\n"), "X")
    assert got == Outer(budget=(1, 3), p=1.0, inner=Inner(dt=2.0))
    assert type(got.p) is float and type(got.inner.dt) is float and got.budget == (1, 3)
    assert got.sizes == (1.0, 2.0) and got.maybe is None and got.width_m == 2.0
    got = read_section(Outer, {"BUDGET": [2, 2], "MAYBE": {}, "COUNT": 3, "WIDTH": 5})
    assert got.maybe == Inner() and got.count == 3 and got.width_m == 5.0
    assert read_section(Inner, None, "INNER") == Inner()


@pytest.mark.parametrize(
    "body, message",
    [
        ("P: 0.5\n", r"missing required key SEC\.BUDGET \(in .*sec\.yaml\)"),
        ("BUDGET: [1, 2]\nWIDHT: 3\n", r"unknown key 'WIDHT' in SEC \(from .*sec\.yaml\); allowed"),
        ("BUDGET: [3, 2]\n", r"SEC\.BUDGET = \[3, 2\] \(from .*sec\.yaml\): expected \[lo, hi\]"),
        ("BUDGET: [1.0, 2]\n", r"SEC\.BUDGET = \[1\.0, 2\]"),
        ("BUDGET: [1, 2]\nP: 2.0\n", r"SEC\.P = 2\.0 \(.*\): expected a number in \[0, 1\]$"),
        ("BUDGET: [1, 2]\nP: .nan\n", r"SEC\.P = nan .*\(a finite number\)"),
        ("BUDGET: [1, 2]\nP: true\n", r"SEC\.P = True"),
        ("BUDGET: [1, 2]\nP: '0.5'\n", r"SEC\.P = '0\.5'"),
        ("BUDGET: [1, 2]\nMODE: c\n", r"SEC\.MODE = 'c' .*: expected one of 'a', 'b'"),
        ("BUDGET: [1, 2]\nSIZES: [1.0, -1.0]\n", r"SEC\.SIZES = .*expected a list of numbers > 0"),
        ("BUDGET: [1, 2]\nENABLED: 1\n", r"SEC\.ENABLED = 1 .*expected true or false"),
        ("BUDGET: [1, 2]\nINNER:\n  DT: 0\n", r"SEC\.INNER\.DT = 0 \(from .*sec\.yaml\)"),
        ("BUDGET: [1, 2]\nINNER: 3\n", r"SEC\.INNER = 3 .*expected"),
        ("BUDGET: [1, 2]\nINNER:\n  DX: 0\n", r"unknown key 'DX' in SEC\.INNER \(from .*sec"),
        ("BUDGET: [1, 2]\nCOUNT: -1\n", r"SEC\.COUNT = -1 .*an integer >= 0"),
        ("BUDGET: [1, 2]\nENABLED: true\n", r"SEC \(from .*sec\.yaml\): ENABLED needs MODE b"),
    ],
)
def test_errors_name_file_key_value_and_expectation(tmp_path, body, message):
    with pytest.raises(ConfigError, match=message):
        read_section(Outer, load(tmp_path, body), "SEC")


def test_where_names_the_section_of_top_level_keys(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key 'Q' in attack config X \(from"):
        read_section(Outer, load(tmp_path, "BUDGET: [1, 2]\nQ: 1\n"), where="attack config X")
    with pytest.raises(ConfigError, match=r"^P = 3 "):  # top level: the key alone
        read_section(Outer, {"BUDGET": [1, 2], "P": 3})
    assert read_section(Outer, {"BUDGET": [1, 2], "NAME": "x"}, ignore=["NAME"]).p == 0.01


def test_declared_keys_settings_and_defaults():
    keys = declared_keys(Outer)
    assert keys[:3] == ["BUDGET", "P", "MODE"] and "INNER.DT" in keys and "WIDTH" in keys
    rows = {key: (default, doc) for key, default, doc in declared_settings(Outer)}
    assert rows["BUDGET"][0] is REQUIRED and rows["INNER.DT"] == (0.1, "s per frame")
    assert declared_defaults(Outer)["inner"] == Inner() and "budget" not in declared_defaults(Outer)


# ------------------------------------------------------------------ the declarations in use
def declared_components() -> list[tuple[type, type]]:
    """``(class, declaration)`` of the classes built from a declared section, whose keyword
    arguments share the declaration's field names."""
    import pcdet_atlas.attacks  # noqa: F401
    from pcdet_atlas.attacks.base import BaseAttack
    from pcdet_atlas.attacks.ground import GroundConfig, GroundEstimator
    from pcdet_atlas.attacks.intensity import IntensityConfig, RangeIntensityModel
    from pcdet_atlas.attacks.tracking import Tracker, TrackingConfig
    from pcdet_atlas.registry import ATTACKS

    pairs = [
        (GroundEstimator, GroundConfig),
        (RangeIntensityModel, IntensityConfig),
        (Tracker, TrackingConfig),
        (BaseAttack, BaseAttack.CONFIG),
    ]
    pairs += [(cls, cls.CONFIG) for _, cls in ATTACKS.items()]
    pairs += [(cls, cls.CONFIG) for cls in model_stage_classes()]
    return pairs


def model_stage_classes() -> list[type]:
    """Every registered model stage with a declaration (``CONFIG``)."""
    import pcdet_atlas.models  # noqa: F401
    from pcdet_atlas import registry

    found = []
    for reg in vars(registry).values():
        if isinstance(reg, registry.Registry):
            found += [
                cls for _, cls in reg.items() if isinstance(getattr(cls, "CONFIG", None), type)
            ]
    return found


def test_constructor_defaults_are_the_declared_defaults():
    """Defaults live in the declaration: a constructor keyword of the same name defaults to the
    declared value (a notebook user and a YAML that leaves the key out get the same)."""
    checked, wrong = 0, []
    for cls, decl in dict.fromkeys(declared_components()):
        defaults = declared_defaults(decl)
        for name, param in inspect.signature(cls.__init__).parameters.items():
            if name not in defaults or param.default is inspect.Parameter.empty:
                continue
            if param.default is None and is_declaration(type(defaults[name])):
                continue  # None: built from the section's declared defaults
            if defaults[name] is None:
                continue  # derived when built (IOU_WEIGHT: from the number of classes)
            checked += 1
            if param.default != defaults[name]:
                wrong.append(
                    f"{cls.__name__}({name}={param.default!r}): declared {defaults[name]!r}"
                )
    assert not wrong, "\n".join(wrong)
    assert checked >= 20, checked


# ------------------------------------------------------------------ DATA_CONFIG
DATASET_BASE = "cfgs/dataset_configs/synthetic_waymo.yaml"


@pytest.mark.parametrize(
    "body, message",
    [
        # values a hand-written bool() / int() used to read silently ('no' is truthy)
        ("TRAIN_WITH_SPEED: 'no'\n", r"DATA_CONFIG\.TRAIN_WITH_SPEED = 'no' \(from .*bad\.yaml\)"),
        (
            "DATA_PROCESSOR:\n  - NAME: mask_points_and_boxes_outside_range\n    FILTER_Z: 'no'\n",
            r"mask_points_and_boxes_outside_range\.FILTER_Z = 'no' \(from .*bad\.yaml",
        ),
        (
            "SEQUENCE_CONFIG:\n  ENABLED: True\n  SAMPLE_OFFSET: [-3, 1]\n",
            r"DATA_CONFIG\.SEQUENCE_CONFIG\.SAMPLE_OFFSET = \[-3, 1\] .*expected \[-k, 0\]",
        ),
        ("POINTS_TANH_DIM: [7]\n", r"DATA_CONFIG\.POINTS_TANH_DIM = \[7\] .*column indices 0-4"),
        (
            "POINT_CLOUD_RANGE: [0, 0, 0, 1, 1]\n",
            r"DATA_CONFIG\.POINT_CLOUD_RANGE = \[0, 0, 0, 1, 1\]",
        ),
        ("SEED: 1.5\n", r"DATA_CONFIG\.SEED = 1\.5 .*expected an integer"),
        ("USE_SHARED_MEMORY: True\n", r"DATA_CONFIG\.USE_SHARED_MEMORY = True .*read from disk"),
    ],
)
def test_bad_dataset_values_name_key_value_and_file(tmp_path, body, message):
    from pcdet_atlas.config import REPO_ROOT
    from pcdet_atlas.datasets.waymo_dataset import WaymoDataset

    path = tmp_path / "bad.yaml"
    path.write_text(f"_BASE_CONFIG_: {REPO_ROOT / DATASET_BASE}\n{body}")
    cfg = cfg_from_yaml_file(path)
    root = REPO_ROOT / "data" / "synthetic_waymo"
    with pytest.raises(ConfigError, match=message):
        WaymoDataset(cfg, ["Vehicle"], training=False, root_path=root)


# ------------------------------------------------ MODEL, OPTIMIZATION, STAGE, ATLAS, sensor
MODEL_CFG = "cfgs/atlas/synthetic/centerpoint.yaml"


def model_yaml(tmp_path, body: str, base: str = MODEL_CFG):
    from pcdet_atlas.config import REPO_ROOT

    path = tmp_path / "bad.yaml"
    path.write_text(f"_BASE_CONFIG_: {REPO_ROOT / base}\n{body}")
    return cfg_from_yaml_file(path)


@pytest.mark.parametrize(
    "body, message",
    [
        ("MODEL:\n  POST_PROCESSING:\n    SCORE_THRESH: 0.3\n",
         r"MODEL\.POST_PROCESSING\.SCORE_THRESH = 0\.3 \(from .*bad\.yaml\): expected null "
         r"\(a one-stage detector's threshold is its DENSE_HEAD"),
        ("MODEL:\n  POST_PROCESSING:\n    EVAL_METRIC: kitti\n",
         r"MODEL\.POST_PROCESSING\.EVAL_METRIC = 'kitti' \(from .*bad\.yaml\)"),
        ("MODEL:\n  POST_PROCESSING:\n    OUTPUT_RAW_SCORE: true\n",
         r"MODEL\.POST_PROCESSING\.OUTPUT_RAW_SCORE = True \(from .*bad\.yaml\)"),
        ("MODEL:\n  RPN:\n    CFG: x.yaml\n", r"unknown key 'RPN' in MODEL \(from .*bad\.yaml"),
        ("MODEL:\n  VFE:\n    NAME: 3\n", r"MODEL\.VFE\.NAME = 3 \(from .*bad\.yaml\)"),
    ],
)  # fmt: skip
def test_bad_model_keys_name_key_value_and_file(tmp_path, body, message):
    from pcdet_atlas.models import build_network_from_config

    with pytest.raises(ConfigError, match=message):
        build_network_from_config(model_yaml(tmp_path, body))


def test_model_without_a_required_stage_or_class_names_names_the_key(tmp_path):
    from pcdet_atlas.models import build_network_from_config

    cfg = model_yaml(tmp_path, "")
    del cfg.MODEL["DENSE_HEAD"]
    missing = r"missing required key MODEL\.DENSE_HEAD .*centerpoint\.yaml"
    with pytest.raises(ConfigError, match=missing):
        build_network_from_config(cfg)
    cfg = model_yaml(tmp_path, "CLASS_NAMES: []\n")
    with pytest.raises(ConfigError, match=r"CLASS_NAMES = \[\] \(from .*bad\.yaml\)"):
        build_network_from_config(cfg)


def test_two_stage_post_processing_is_read_into_its_declaration(tmp_path):
    """MSF's NMS values reach the detector as the declaration read them (and their defaults
    when absent): what ``TwoStageDetector.detections`` thresholds with."""
    from pcdet_atlas.models.detectors.two_stage import (
        RPNConfig,
        TwoStageConfig,
        TwoStageNMSConfig,
    )

    cfg = model_yaml(
        tmp_path,
        "MODEL:\n  POST_PROCESSING:\n    SCORE_THRESH: 0.25\n    NMS_CONFIG:\n"
        "      NMS_THRESH: 0.5\n",
        base="cfgs/atlas/synthetic/msf_4f.yaml",
    )
    settings = read_section(TwoStageConfig, cfg.MODEL, "MODEL", ignore=["ROI_HEAD"])
    post = settings.post_processing
    assert post.score_thresh == 0.25 and post.not_apply_nms_for_vel is True
    assert post.nms_config == TwoStageNMSConfig(nms_thresh=0.5)  # the rest at the defaults
    assert isinstance(settings.rpn, RPNConfig) and settings.rpn.cfg.endswith("cp4f.yaml")
    del cfg.MODEL["RPN"]
    with pytest.raises(ConfigError, match=r"missing required key MODEL\.RPN \(in .*bad\.yaml"):
        read_section(TwoStageConfig, cfg.MODEL, "MODEL", ignore=["ROI_HEAD"])


@pytest.mark.parametrize(
    "body, message",
    [
        ("OPTIMIZATION:\n  WARMUP_EPOCH: 1.5\n", r"OPTIMIZATION\.WARMUP_EPOCH = 1\.5 .*integer"),
        ("OPTIMIZATION:\n  LR_WARMUP: 'yes'\n", r"OPTIMIZATION\.LR_WARMUP = 'yes' .*true or"),
        ("OPTIMIZATION:\n  DECAY_STEP_LIST: 5\n", r"OPTIMIZATION\.DECAY_STEP_LIST = 5 .*list"),
        ("OPTIMIZATION:\n  LR_DECAY: 0\n", r"OPTIMIZATION\.LR_DECAY = 0 .*> 0"),
    ],
)
def test_bad_optimization_values_name_key_value_and_file(tmp_path, body, message):
    """Values the hand-written reads took as they came (``int(1.5)``, a truthy ``'yes'``)."""
    from pcdet_atlas.models.optimization import check_optimization_config

    with pytest.raises(ConfigError, match=message) as err:
        check_optimization_config(model_yaml(tmp_path, body).OPTIMIZATION)
    assert "bad.yaml" in str(err.value)


@pytest.mark.parametrize(
    "body, message",
    [
        ("STAGE:\n  NAME: s\n  TRAIN: lot\n", r"STAGE\.TRAIN = 'lot' \(from .*bad\.yaml\)"),
        ("STAGE:\n  NAME: s\n  TRAIN: []\n", r"STAGE\.TRAIN = \[\] .*must train something"),
        ("STAGE:\n  NAME: s\n  TRAIN: [lot]\n  FROZE: [vfe]\n", r"unknown key 'FROZE' in STAGE"),
        ("STAGE:\n  NAME: s\n", r"missing required key STAGE\.TRAIN \(in .*bad\.yaml\)"),
        ("ATLAS:\n  TEMPORAL_WINDOW: 0\n", r"ATLAS\.TEMPORAL_WINDOW = 0 \(from .*bad\.yaml\)"),
        ("ATLAS:\n  TRAINING_SEED: '7'\n", r"ATLAS\.TRAINING_SEED = '7' \(from .*bad\.yaml\)"),
        ("ATLAS:\n  CHECKPOIN: x.pth\n", r"unknown key 'CHECKPOIN' in ATLAS \(from .*bad\.yaml"),
    ],
)
def test_bad_stage_and_atlas_values_name_key_value_and_file(tmp_path, body, message):
    from pcdet_atlas.train_utils.atlas_eval import atlas_section
    from pcdet_atlas.train_utils.stages import stage_from_config

    cfg = model_yaml(tmp_path, body)
    with pytest.raises(ConfigError, match=message):
        stage_from_config(cfg) if "STAGE" in cfg else atlas_section(cfg.ATLAS)


def test_sensor_model_reads_its_section(tmp_path):
    from pcdet_atlas.datasets.synthetic.sensor import SensorModel

    path = tmp_path / "sensor.yaml"
    path.write_text("SENSOR:\n  DROP_PROB: 0.1\n")
    assert SensorModel.from_config(cfg_from_yaml_file(path).SENSOR) == SensorModel(drop_prob=0.1)
    path.write_text("SENSOR:\n  DROP_PROB: 1.5\n")
    with pytest.raises(ConfigError, match=r"SENSOR\.DROP_PROB = 1\.5 \(from .*sensor\.yaml\)"):
        SensorModel.from_config(cfg_from_yaml_file(path).SENSOR)
