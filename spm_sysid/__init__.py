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
    "CRITERIA": "core.fit.criteria",
    "Criterion": "core.fit.criteria",
    "get_criterion": "core.fit.criteria",
    "make_pmic2": "core.fit.criteria",
    "register_criterion": "core.fit.criteria",
    "DataError": "core.errors",
    "load_io": "core.io.data",
    "load_data": "core.io.data",
    "load_robot_arm": "core.io.datasets",
    "GAConfig": "core.search.ga",
    "GAResult": "core.search.ga",
    "run_ga": "core.search.ga",
    "IdentificationResult": "core.identify",
    "identify": "core.identify",
    "NarxModel": "core.model.narx",
    "TermSpace": "core.model.terms",
    "validate_model": "core.validate.validation",
    "ValidationReport": "core.validate.validation",
    "find_segments": "core.model.segments",
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
