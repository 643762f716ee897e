"""The benchmark's methods, settings and reference peers: names shared by every section."""

from __future__ import annotations

METHODS = (
    "pranet-v1",
    "pranet-v2",
    "pranet-v2-http",
    "pranet-adaptive",
    "pranet-adaptive-http",
    "icp",
    "fgr-icp",
    "ransac-icp",
    "ransac-pranet-icp",
    "small-gicp",
)
# (in-process, HTTP) method pairs whose time is broken down by stage
BREAKDOWN_PAIRS = (("pranet-v2", "pranet-v2-http"), ("pranet-adaptive", "pranet-adaptive-http"))
PRANET_IN_PROCESS = ("pranet-v1", "pranet-v2")
REFERENCES = ("ransac-icp", "fgr-icp")  # latency ratios are taken against these
DEFAULT_SETTINGS = ("noisy", "partial")
SMALL_GICP_DOWNSAMPLING = 0.01  # unit-sphere shapes: keeps (almost) every point
SERVER_START_TIMEOUT_S = 120.0
