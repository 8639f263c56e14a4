"""spm_sysid: polynomial NARX identification by a GA with single parent mating.

The public Python API (no ROS needed)::

    from spm_sysid import identify, load_robot_arm
    u, y = load_robot_arm()
    result = identify(u=u, y=y, criterion="aic", seed=1)
    print(result.model.equation())
"""

__version__ = "0.1.0"

from .core.criteria import CRITERIA, Criterion, get_criterion, make_pmic2, register_criterion
from .core.data import DataError, load_io, load_robot_arm
from .core.ga import GAConfig, GAResult, run_ga
from .core.identify import IdentificationResult, identify
from .core.model import NarxModel
from .core.terms import TermSpace

__all__ = [
    "CRITERIA",
    "Criterion",
    "DataError",
    "GAConfig",
    "GAResult",
    "IdentificationResult",
    "NarxModel",
    "TermSpace",
    "__version__",
    "get_criterion",
    "identify",
    "load_io",
    "load_robot_arm",
    "make_pmic2",
    "register_criterion",
    "run_ga",
]
