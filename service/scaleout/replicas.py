"""What a call into another deployment's replica raises while that replica is dead or being replaced
(docs/scaling.md "Failure"; docs/design/service.md §9): the one list both callers use, the ingress
calling a shard (`ShardSet.call` -> `ShardUnavailable`) and a shard calling the encoder
(`PendingReply.result` -> `EncoderUnavailable`). Ray is imported only where it is installed.
"""

from __future__ import annotations

import asyncio
import contextlib

__all__ = ["unavailable_errors"]


def unavailable_errors() -> tuple[type[BaseException], ...]:
    """A timeout and a lost connection; with Ray: an actor that died or does not answer (`RayActorError`:
    `ActorDiedError`, `ActorUnavailableError`), a worker or node that died with the call, and Serve's own
    errors (`RayServeException`: no replica, a replica gone, a request cancelled with it, an upstream
    replica that died), none of which is the app's answer."""
    errors: tuple[type[BaseException], ...] = (asyncio.TimeoutError, ConnectionError)
    with contextlib.suppress(ImportError):
        from ray.exceptions import NodeDiedError, RayActorError, WorkerCrashedError
        from ray.serve.exceptions import RayServeException

        errors += (RayActorError, WorkerCrashedError, NodeDiedError, RayServeException)
    return errors
