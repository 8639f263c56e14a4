"""Online use of an identified model on a live stream (no ROS here).

* :mod:`.predictor` -- one-step prediction sample by sample;
* :mod:`.monitor` -- is the model still valid? (residual RMS, whiteness, CUSUM);
* :mod:`.tracker` -- recursive least squares on the model's structure.

The node (:mod:`spm_sysid.ros.sysid_node`) feeds them each paired sample.
"""

from .monitor import MonitorState, ValidityMonitor
from .predictor import OnlinePredictor
from .tracker import RecursiveTracker

__all__ = ["MonitorState", "OnlinePredictor", "RecursiveTracker", "ValidityMonitor"]
