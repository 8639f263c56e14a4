"""spm_sysid: polynomial NARX identification by a GA with single parent mating.

The public Python API (no ROS needed)::

    from . import identify
    from .core.io.datasets import load_robot_arm
    u, y = load_robot_arm()
    result = identify(u=u, y=y, criterion="aic", seed=1)
    print(result.model.equation())

Names are imported lazily, so ``import spm_sysid.tools.cli`` can configure the
process (BLAS threads) before numpy loads.
"""

from importlib import import_module

__version__ = "0.1.0"

_API = {
    "CRITERIA": "core.narx.criteria",
    "Criterion": "core.narx.criteria",
    "get_criterion": "core.narx.criteria",
    "make_pmic2": "core.narx.criteria",
    "register_criterion": "core.narx.criteria",
    "DataError": "core.errors",
    "load_io": "core.io.data",
    "load_data": "core.io.data",
    "load_robot_arm": "core.io.datasets",
    "GAConfig": "core.narx.ga",
    "GAResult": "core.narx.ga",
    "run_ga": "core.narx.ga",
    "IdentificationResult": "core.narx.identify",
    "identify": "core.narx.identify",
    "NarxModel": "core.narx.model",
    "TermSpace": "core.narx.terms",
    "validate_model": "core.narx.validation",
    "ValidationReport": "core.narx.validation",
    "find_segments": "core.narx.segments",
    "read_bag_signals": "core.io.bagio",
    "write_io_bag": "core.io.bagio",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        return getattr(import_module(f".{_API[name]}", __name__), name)
    raise AttributeError(f"module 'spm_sysid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
