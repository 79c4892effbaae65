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
    for reg in (DATASETS, TRANSFORMS, ATTACKS, DETECTORS, MODEL_STAGES):
        assert isinstance(reg.list(), list)
