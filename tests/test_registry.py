import json
import subprocess
import sys

import pytest

from pcdet_atlas.registry import (
    ATTACKS,
    DATASETS,
    DETECTORS,
    MODEL_STAGES,
    TRANSFORMS,
    Registry,
    RegistryError,
)


def test_register_get_list():
    reg = Registry("widget")

    @reg.register()
    class Foo:
        pass

    @reg.register("bar")
    def make_bar():
        return 1

    assert reg.get("Foo") is Foo
    assert reg.get("bar") is make_bar
    assert reg.list() == ["Foo", "bar"]
    assert "Foo" in reg and len(reg) == 2


def test_duplicate_name_raises():
    reg = Registry("widget")

    @reg.register("X")
    class A:
        pass

    with pytest.raises(RegistryError, match="already registered"):

        @reg.register("X")
        class B:
            pass

    # re-registering the very same object is harmless (module reload)
    reg.register("X")(A)


def test_a_taken_name_names_both_instances():
    """Analyses and confidence kinds register instances, which have no ``__qualname__``: the
    error still names both (it was an AttributeError)."""
    from pcdet_atlas.evaluation.analyses import ConfidenceKind, register_confidence_kind

    class Kind:
        pass

    reg = Registry("thing")
    reg.register("k")(Kind())
    with pytest.raises(RegistryError, match=r"'k' is already registered to an instance of .*Kind;"
                       r" cannot register an instance of .*Kind"):  # fmt: skip
        reg.register("k")(Kind())
    with pytest.raises(RegistryError, match="'injection' is already registered"):
        register_confidence_kind(
            ConfidenceKind(name="injection", compute=lambda data: {}, shown="x")
        )


def test_unknown_name_lists_known_and_suggests():
    reg = Registry("attack")
    reg.register("InjectionAttack")(type("InjectionAttack", (), {}))
    reg.register("RemovalAttack")(type("RemovalAttack", (), {}))
    with pytest.raises(RegistryError) as err:
        reg.get("InjectionAtack")
    msg = str(err.value)
    assert "unknown attack 'InjectionAtack'" in msg
    assert "InjectionAttack, RemovalAttack" in msg
    assert "Did you mean 'InjectionAttack'" in msg


def test_global_registries_exist_and_autoload():
    """A process that imports only the registry module finds the built-ins on first lookup."""
    code = (
        "import json; from pcdet_atlas import registry as r; print(json.dumps({n: getattr(r, n)"
        ".list() for n in ('DATASETS', 'TRANSFORMS', 'ATTACKS', 'DETECTORS', 'MODEL_STAGES')}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    listed = json.loads(out.strip().splitlines()[-1])
    assert {"WaymoDataset", "AtlasWaymoDataset"} <= set(listed["DATASETS"])
    assert {"gt_sampling", "random_world_flip", "shuffle_points"} <= set(listed["TRANSFORMS"])
    assert {"CleanAttack", "InjectionAttack", "RemovalAttack"} <= set(listed["ATTACKS"])
    assert {"CenterPoint", "MSF", "PTT", "PHiM"} <= set(listed["DETECTORS"])
    assert {"CenterHead", "VoxelResBackBone8x", "LatentOccupancyTracking"} <= set(
        listed["MODEL_STAGES"]
    )
    # the same built-ins in this process (where other tests may have registered more)
    for name, reg in zip(listed, (DATASETS, TRANSFORMS, ATTACKS, DETECTORS, MODEL_STAGES)):
        assert set(listed[name]) <= set(reg.list()), name


def test_items_keep_the_registration_order_and_unregister_undoes_one():
    reg = Registry("widget")
    for name in ("b", "a", "c"):
        reg.register(name)(type(name, (), {}))
    assert [name for name, _ in reg.items()] == ["b", "a", "c"] and reg.list() == ["a", "b", "c"]
    removed = reg.unregister("a")
    assert removed.__name__ == "a" and [name for name, _ in reg.items()] == ["b", "c"]
    with pytest.raises(RegistryError, match="unknown widget 'a'"):
        reg.unregister("a")
