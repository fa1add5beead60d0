"""The exception types of every layer, in one module that each of them imports (it imports
nothing of the package). The APIs map them to status codes: api/rest.py and api/grpc_api.py.

DatabaseUnavailable and DatabaseBusy stay in infra/store.py: they are psycopg OperationalErrors
(so that handlers of database failures catch them), and defining them here would load psycopg
into every import of the client.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .domain.states import JobState


class SettingsError(ValueError):
    """A job setting is unknown or out of range. `field` names it (e.g. "settings.max_spp")."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field
        self.message = message


class TransitionError(ValueError):
    """A state change TRANSITIONS does not allow (the APIs answer 409 Conflict)."""

    def __init__(self, old: JobState, new: JobState):
        super().__init__(f"a {old.value} job cannot become {new.value}")
        self.old = old
        self.new = new


class SceneError(ValueError):
    """A scene was refused.  The message is meant for the user; ``field`` says where."""

    def __init__(self, message: str, field: str = "scene") -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class NotFound(LookupError):
    """Something the request names does not exist; `field` names the part of the request
    when it is not the job itself (e.g. "frame": a frame the job does not render)."""

    def __init__(self, what: str, field: str = ""):
        super().__init__(what)
        self.message = what
        self.field = field


class TooLarge(ValueError):
    def __init__(self, field_name: str, message: str):
        super().__init__(message)
        self.field = field_name
        self.message = message


class Unauthenticated(PermissionError):
    """A worker's token is wrong or missing (gRPC UNAUTHENTICATED)."""


class Conflict(RuntimeError):
    """The request is valid but the job's state does not allow it (REST 409)."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class LeaseLost(Conflict):
    """A write of a job's owner was refused: the job's lease in the database no longer names
    this replica at the epoch the write carried (another replica took the job over, #39). The
    service drops the job from memory (its unsaved merges with it) and leaves it to its new
    owner; an API request that meets it is answered 409 and may be sent again."""

    def __init__(self, job_ids: list[str] | str, message: str = ""):
        self.job_ids = [job_ids] if isinstance(job_ids, str) else list(job_ids)
        super().__init__(
            message or f"job {', '.join(self.job_ids)} is owned by another server now; try again"
        )


class AuthError(PermissionError):
    """No token, or one that is unknown or revoked (REST 401, gRPC UNAUTHENTICATED)."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class Forbidden(PermissionError):
    """A valid token that may not do this (REST 403, gRPC PERMISSION_DENIED)."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class Cancelled(RuntimeError):
    """The server is stopping: an image being written is abandoned."""


class SchemaTooNew(RuntimeError):
    """The database was migrated by a newer server than this one."""


__all__ = [
    "AuthError",
    "Cancelled",
    "Conflict",
    "Forbidden",
    "LeaseLost",
    "NotFound",
    "SceneError",
    "SchemaTooNew",
    "SettingsError",
    "TooLarge",
    "TransitionError",
    "Unauthenticated",
]
