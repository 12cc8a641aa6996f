"""``LinearTracking``, exact tracking of a linear plant at long horizons, and the named structures its
problem searches over: ``Node`` (a search node), ``TrackingModel`` (the plant), ``TrackingParams`` (what
changes every step) and ``SharedParams`` (model and step values together, for ``shared_problem``)."""
from ._src.linear.tracking import LinearTracking, Node, SharedParams, TrackingModel, TrackingParams

__all__ = ["LinearTracking", "Node", "TrackingModel", "TrackingParams", "SharedParams"]
