"""spm_sysid: polynomial NARX identification by a GA with single parent mating.

The public Python API (no ROS needed)::

    from spm_sysid import identify, load_robot_arm
    u, y = load_robot_arm()
    result = identify(u=u, y=y, criterion="aic", seed=1)
    print(result.model.equation())

Names are imported lazily, so ``import spm_sysid.tools.cli`` can configure the
process (BLAS threads) before numpy loads.
"""

from importlib import import_module

__version__ = "0.1.0"

_API = {
    "CRITERIA": "core.criteria",
    "Criterion": "core.criteria",
    "get_criterion": "core.criteria",
    "make_pmic2": "core.criteria",
    "register_criterion": "core.criteria",
    "DataError": "core.data",
    "load_io": "core.data",
    "load_robot_arm": "core.data",
    "GAConfig": "core.ga",
    "GAResult": "core.ga",
    "run_ga": "core.ga",
    "IdentificationResult": "core.identify",
    "identify": "core.identify",
    "NarxModel": "core.model",
    "TermSpace": "core.terms",
    "validate_model": "core.validation",
    "ValidationReport": "core.validation",
    "read_bag_signals": "core.bagio",
    "write_io_bag": "core.bagio",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        return getattr(import_module(f".{_API[name]}", __name__), name)
    raise AttributeError(f"module 'spm_sysid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
