"""The registry of `[plant] engine`: which physics plays the robot in the deployed controller's sampled loop."""

from __future__ import annotations

from ..core.errors import InputError
from ..core.registry import Registry

ENGINES = Registry("plant engine", "plant.engine")

ENGINES.add("symfunnel", "symfunnel's own plant: the controller's M, C, G (times plant.mass_scale) with the [plant] "
                         "nonlinearities, integrated by CasADi's RK4 (the default)", "symfunnel")
ENGINES.add("mujoco", "MuJoCo as the robot: the URDF read by MuJoCo's own parser (planar and dh models: MJCF written "
                      "from the link tree), stepped by MuJoCo's implicitfast (or RK4); needs pip install "
                      "'symfunnel[mujoco]'", "mujoco")

#: model types a physics engine can load (a `matrices` model gives no geometry or inertias)
ENGINE_MODEL_TYPES = ("planar", "dh", "urdf")
#: MuJoCo 4 (mj_fullM(m, d, dst), no mjData.qM, URDF strippath off by default)
MIN_VERSION = 4000000


def require_mujoco(*, file: str | None = None, key: str = "plant.engine"):
    """The mujoco module (MuJoCo >= 4), or an InputError saying how to install it."""
    try:
        import mujoco
    except ImportError:
        raise InputError("is 'mujoco' but the mujoco package is not installed", file=file, key=key,
                         expected="pip install 'symfunnel[mujoco]' (MuJoCo 4)") from None
    if mujoco.mj_version() < MIN_VERSION:
        raise InputError(f"is 'mujoco' but MuJoCo {mujoco.mj_versionString()} is installed", file=file, key=key,
                         expected="MuJoCo >= 4 (pip install 'symfunnel[mujoco]')")
    return mujoco


def check_engine_model(model, engine: str, *, file: str | None, key: str) -> None:
    """An engine other than symfunnel's needs a model with link geometry and inertias (planar, dh or urdf)."""
    if engine != "symfunnel" and getattr(model, "kind", None) not in ENGINE_MODEL_TYPES:
        raise InputError(f"is '{engine}' but the model is of type '{model.kind}', which gives no link geometry or "
                         "inertias for a physics engine", file=file, key=key,
                         expected="a urdf, planar or dh model (or the engine 'symfunnel')")


def resolve_engine(scenario, override: str | None = None, *, key: str = "--plant") -> str:
    """The engine a command runs on: `override` (a --plant value) or the scenario's `[plant] engine`, validated
    (a did-you-mean for an unknown name, the model type, and for MuJoCo that the package is installed)."""
    if override is None:
        engine, file, key = scenario.plant.engine, scenario.file, "plant.engine"
    else:
        engine, file = override, None
        ENGINES.get(engine, file=file, key=key)
    check_engine_model(scenario.model, engine, file=file if override is None else scenario.file, key=key)
    if engine == "mujoco":
        require_mujoco(file=file, key=key)
    return engine
