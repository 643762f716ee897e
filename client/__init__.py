"""HTTP client and command-line tool (``pranet-client``) for the PRANet registration service."""

from pranet.client.client import (
    PranetClient,
    PranetConnectionError,
    PranetError,
    RegistrationResult,
    TrajectoryStep,
    encode_cloud,
)
from pranet.client.io import PointCloudIOError, read_point_cloud, write_point_cloud

__all__ = [
    "PointCloudIOError",
    "PranetClient",
    "PranetConnectionError",
    "PranetError",
    "RegistrationResult",
    "TrajectoryStep",
    "encode_cloud",
    "read_point_cloud",
    "write_point_cloud",
]
