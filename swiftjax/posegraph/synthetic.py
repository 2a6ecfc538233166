"""Deprecated: the synthetic pose graphs moved to :mod:`swiftjax.synthetic.pose_graphs`."""

import warnings

from swiftjax.synthetic.pose_graphs import *  # noqa: F401,F403
from swiftjax.synthetic.pose_graphs import __all__  # noqa: F401

warnings.warn(
    "swiftjax.posegraph.synthetic is deprecated; import swiftjax.synthetic.pose_graphs",
    DeprecationWarning,
    stacklevel=2,
)
