"""Typed Python client for the cortexloc HTTP API: `Client` (sync) and `AsyncClient` (asyncio).

Replies are pydantic models (`cortexloc_client.models`); refusals are `CortexlocError` and its
subclasses, and so is a success reply the client cannot read (`InvalidResponseError`); the service's
503s are retried after `Retry-After` (`RetryPolicy`); observation posts carry an `Idempotency-Key`, the
same across their retries, and are resent with it on a proxy's 500, 502, 503 or 504 page, or on a reply
the client cannot read.
"""

import pydantic

if not pydantic.VERSION.startswith("2."):
    # ROS 2's apt packages (Ubuntu 22.04 and 24.04) ship pydantic 1, which fails deep inside the models
    # with an error that does not name the cause.
    raise ImportError(f"cortexloc_client needs pydantic 2, found pydantic {pydantic.VERSION} at "
                      f"{pydantic.__file__}: install the client in a virtual environment (its README: "
                      f"'Beside ROS 2')")

from cortexloc_client._core import RetryPolicy, Settings, __version__
from cortexloc_client.aio import AsyncClient
from cortexloc_client.client import Client
from cortexloc_client.errors import (
    BadRequestError,
    ConflictError,
    CortexlocError,
    InsufficientStorageError,
    InvalidResponseError,
    NotFoundError,
    PayloadTooLargeError,
    ServerError,
    ServiceUnavailableError,
    TooManyRequestsError,
    UnauthorizedError,
    UnprocessableError,
    UnsupportedMediaTypeError,
)
from cortexloc_client.frames import ColourOrder, frame_body
from cortexloc_client.models import (
    MAX_TOP_K,
    POSE_MAX_ABS,
    STREAM_PATTERN,
    YAW_MAX_ABS,
    Budget,
    Map,
    Match,
    Memory,
    Metadata,
    Observation,
    Place,
    Pose,
    Readiness,
    RestoredMap,
    Snapshot,
    StoredObservation,
    StoredObservationList,
    Verification,
)

__all__ = [
    "MAX_TOP_K",
    "POSE_MAX_ABS",
    "STREAM_PATTERN",
    "YAW_MAX_ABS",
    "AsyncClient",
    "BadRequestError",
    "Budget",
    "Client",
    "ColourOrder",
    "ConflictError",
    "CortexlocError",
    "InsufficientStorageError",
    "InvalidResponseError",
    "Map",
    "Match",
    "Memory",
    "Metadata",
    "NotFoundError",
    "Observation",
    "PayloadTooLargeError",
    "Place",
    "Pose",
    "Readiness",
    "RestoredMap",
    "RetryPolicy",
    "ServerError",
    "ServiceUnavailableError",
    "Settings",
    "Snapshot",
    "StoredObservation",
    "StoredObservationList",
    "TooManyRequestsError",
    "UnauthorizedError",
    "UnprocessableError",
    "UnsupportedMediaTypeError",
    "Verification",
    "__version__",
    "frame_body",
]
