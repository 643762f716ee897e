"""HTTP client and command-line tool (``pranet-client``) for the PRANet registration service."""

from pranet.client.batch import BatchSummary, Pair, RetryPolicy, read_pairs
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
    "BatchSummary",
    "Pair",
    "PointCloudIOError",
    "PranetClient",
    "PranetConnectionError",
    "PranetError",
    "RegistrationResult",
    "RetryPolicy",
    "TrajectoryStep",
    "encode_cloud",
    "read_pairs",
    "read_point_cloud",
    "write_point_cloud",
]
