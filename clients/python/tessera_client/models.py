"""The bodies of Tessera's HTTP API v1 as dataclasses.

Each model names the OpenAPI schema it mirrors (``SCHEMA``); tests/test_openapi.py checks
every field's name, type, nullability and enum against ``/api/v1/openapi.json``, so a
field added to or removed from the server shows up as a failing test rather than as a
silently dropped value.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

#: ``JobStatus.state`` values; ``done``, ``failed`` and ``canceled`` are final.
JOB_STATES = ("queued", "running", "done", "failed", "canceled")
#: The states a job does not leave.
FINAL_STATES = ("done", "failed", "canceled")
#: ``JobSettings.adaptive`` values.
ADAPTIVE_MODES = ("off", "sequential", "unbiased")
#: ``JobSettings.integrator`` values.
INTEGRATORS = ("auto", "path", "direct", "bdpt", "vcm", "ppm", "mlt", "mnee")
#: ``JobSettings.sampler`` values.
SAMPLERS = ("sobol", "independent")
#: ``Error.error.code`` values.
ERROR_CODES = (
    "invalid_field",
    "invalid_request",
    "invalid_scene",
    "unauthorized",
    "not_found",
    "conflict",
    "too_large",
    "insufficient_storage",
    "request_timeout",
    "internal",
    "unavailable",
)


#: How far a running job's ETA can be trusted (``JobStatus.eta_tail_class``).
ETA_TAIL_CLASSES = ("light", "heavy", "unpredictable")


def _enum(values):
    """Field metadata: the values the schema's enum allows."""
    return {"enum": tuple(values)}


@dataclass
class FrameRange:
    """An inclusive range of frames (``JobSettings.frames``)."""

    start: int
    end: int

    def count(self) -> int:
        """How many frames the range holds."""
        return self.end - self.start + 1 if self.end >= self.start else 0


@dataclass
class JobSettings:
    """The body of ``POST /api/v1/jobs`` (schema ``JobSettings``).

    ``None`` fields are left out of the request, so the server's defaults apply; the
    defaults here are the server's (docs/api.md, docs/rendering.md).
    """

    SCHEMA = "JobSettings"

    scene: str
    camera: Optional[str] = None
    width: Optional[int] = None
    height: Optional[int] = None
    spp: int = 64
    integrator: str = field(default="auto", metadata=_enum(INTEGRATORS))
    mis: str = "power"
    sampler: str = field(default="sobol", metadata=_enum(SAMPLERS))
    seed: int = 0
    max_depth: Optional[int] = None
    frames: FrameRange = field(default_factory=lambda: FrameRange(0, 0))
    fps: float = 24.0
    animation: Optional[str] = None
    shutter: Optional[List[float]] = None
    priority: int = 0
    target_error: Optional[float] = None
    adaptive: str = field(default="off", metadata=_enum(ADAPTIVE_MODES))
    min_passes: int = 8
    time_limit_seconds: Optional[float] = None
    tile_size: int = 32
    name: Optional[str] = None
    #: ``{"source": "R,G,B" or an uploaded .hdr/.exr image's hash, "strength",
    #: "rotation_degrees"}`` (:meth:`Client.environment` builds it, uploading the image);
    #: default none, the scene's own lights only (docs/scenes.md#environment-lighting).
    environment: Optional[Dict[str, Any]] = None

    def to_json(self) -> Dict[str, Any]:
        """The request body: every field that is set."""
        out: Dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if isinstance(v, FrameRange):
                v = {"start": v.start, "end": v.end}
            out[f.name] = v
        return out

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "JobSettings":
        """The settings as the server echoes them in a ``JobStatus``."""
        kw = {k: v for k, v in d.items() if k in _names(cls)}
        if isinstance(kw.get("frames"), dict):
            kw["frames"] = FrameRange(kw["frames"]["start"], kw["frames"]["end"])
        return cls(**kw)


def _names(cls) -> set:
    return {f.name for f in dataclasses.fields(cls)}


def _from_json(cls, d: Dict[str, Any]):
    """``cls`` from a JSON object: required fields must be there, unknown ones (a newer
    server's) are ignored."""
    kw = {}
    for f in dataclasses.fields(cls):
        if f.name in d:
            kw[f.name] = d[f.name]
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ValueError(f"{cls.SCHEMA}: the server's answer has no {f.name!r}")
    return cls(**kw)


@dataclass
class SceneUploaded:
    """The answer to ``POST /api/v1/scenes`` (schema ``SceneUploaded``)."""

    SCHEMA = "SceneUploaded"

    hash: str
    bytes: int
    triangles: int
    meshes: int
    materials: int
    lights: int

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "SceneUploaded":
        """Parses the answer."""
        return _from_json(cls, d)


@dataclass
class JobStatus:
    """A job's state and progress (schema ``JobStatus``)."""

    SCHEMA = "JobStatus"

    id: int
    name: Optional[str]
    state: str = field(metadata=_enum(JOB_STATES))
    scene: str
    settings: JobSettings
    width: Optional[int]
    height: Optional[int]
    frames_total: int
    frames_done: int
    tiles_total: int
    passes_planned: int
    passes_done: int
    spp_so_far: float
    error_estimate: Optional[float]
    target_error: Optional[float]
    elapsed_seconds: float
    eta_seconds: Optional[float]
    created_unix_ms: int
    priority: int
    faults: int
    error_estimator: Optional[str] = None
    error_estimate_caveat: Optional[str] = None
    target_reached: Optional[bool] = None
    stop_reason: Optional[str] = None
    started_unix_ms: Optional[int] = None
    finished_unix_ms: Optional[int] = None
    rejected_samples: int = 0
    error: Optional[str] = None
    plan: Optional[Dict[str, Any]] = None
    adaptive: Optional[str] = None
    #: The 95% interval of the seconds until done, for a running job that stops at its
    #: target error; when ``eta_tail_class`` is ``"unpredictable"`` the low end is a lower
    #: bound and there is no ``eta_seconds``.
    eta_low_seconds: Optional[float] = None
    eta_high_seconds: Optional[float] = None
    #: ``light``, ``heavy`` or ``unpredictable``: how far the ETA's laws can be trusted.
    eta_tail_class: Optional[str] = field(default=None, metadata=_enum(ETA_TAIL_CLASSES))
    #: Why the ETA is widened or not predictable, with the measured figures.
    eta_note: Optional[str] = None

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "JobStatus":
        """Parses a job as ``GET /api/v1/jobs/{id}`` answers it."""
        s = _from_json(cls, d)
        if isinstance(s.settings, dict):
            s.settings = JobSettings.from_json(s.settings)
        return s

    @property
    def final(self) -> bool:
        """Whether the job has ended (done, failed or canceled)."""
        return self.state in FINAL_STATES

    def progress_line(self) -> str:
        """One line as ``tessera status`` prints it."""
        err = "-" if self.error_estimate is None else f"{self.error_estimate * 100:.2f}%"
        eta = self.eta_text()
        return (
            f"job {self.id} {self.state}: passes {self.passes_done}/{self.passes_planned}, "
            f"{self.spp_so_far:.1f} spp, error {err}, {self.elapsed_seconds:.1f} s, eta {eta}"
        )


    def eta_text(self) -> str:
        """The ETA as ``tessera status`` gives it: ``12 s``, with its 95% interval for a
        job that stops at its target (``12 s [8, 20 s]``), ``not predictable (at least 5 s,
        at most 120 s)`` when the passes so far cannot predict the error, ``-`` when there
        is none."""
        interval = None
        if self.eta_low_seconds is not None and self.eta_high_seconds is not None:
            interval = (self.eta_low_seconds, self.eta_high_seconds)
        if self.eta_seconds is not None:
            if interval is None:
                return f"{self.eta_seconds:.0f} s"
            return f"{self.eta_seconds:.0f} s [{interval[0]:.0f}, {interval[1]:.0f} s]"
        if interval is not None and self.eta_tail_class == "unpredictable":
            return f"not predictable (at least {interval[0]:.0f} s, at most {interval[1]:.0f} s)"
        return "-"


@dataclass
class QuoteInterval:
    """A prediction and its 95% interval (schema ``QuoteInterval``)."""

    SCHEMA = "QuoteInterval"

    estimate: float
    low: float
    high: float

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "QuoteInterval":
        """Parses the interval."""
        return _from_json(cls, d)


@dataclass
class QuoteTarget:
    """What reaching one target error costs: one row of a quote."""

    #: The target error (relative RMS).
    target: float
    #: Whether the job's planned samples reach it.
    within_plan: bool
    #: Wall seconds on the assumed workers, for the whole job.
    seconds: QuoteInterval
    #: Seconds of one worker on all its threads, for the whole job.
    worker_seconds: QuoteInterval


@dataclass
class Quote:
    """The answer to ``POST /api/v1/jobs?dry_run=true`` (schema ``Quote``), reduced to
    what a submitter shows; ``raw`` is the whole answer."""

    SCHEMA = "Quote"

    fleet: str
    workers: int
    frames: int
    spp: int
    black: bool
    #: The planned samples' cost (``quote.planned``); ``None`` for a black scene.
    planned_seconds: Optional[QuoteInterval]
    planned_error: Optional[QuoteInterval]
    targets: List[QuoteTarget]
    caveat: Optional[str]
    raw: Dict[str, Any]

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "Quote":
        """Parses a dry run's answer."""
        q = d.get("quote") or None
        targets = []
        planned_seconds = planned_error = None
        if q is not None:
            planned_seconds = QuoteInterval.from_json(q["planned"]["seconds"])
            planned_error = QuoteInterval.from_json(q["planned"]["error"])
            for t in q["targets"]:
                targets.append(
                    QuoteTarget(
                        target=t["target"],
                        within_plan=t["within_plan"],
                        seconds=QuoteInterval.from_json(t["cost"]["seconds"]),
                        worker_seconds=QuoteInterval.from_json(t["cost"]["worker_seconds"]),
                    )
                )
        return cls(
            fleet=d["fleet"],
            workers=d["workers"],
            frames=d["frames"],
            spp=d["spp"],
            black=d["black"],
            planned_seconds=planned_seconds,
            planned_error=planned_error,
            targets=targets,
            caveat=d.get("error_estimate_caveat"),
            raw=d,
        )

    def lines(self) -> List[str]:
        """The quote as a few lines of text (the panel and the command line show these)."""
        out = [f"{self.frames} frame(s), {self.spp} spp on {self.fleet}"]
        if self.black:
            out.append("the scene has no light: nothing to render")
            return out
        if self.planned_seconds is not None and self.planned_error is not None:
            out.append(
                f"planned: error {self.planned_error.estimate * 100:.2f}%, "
                f"{_secs(self.planned_seconds)}"
            )
        for t in self.targets:
            plan = "" if t.within_plan else " (beyond the planned spp)"
            out.append(
                f"{t.target * 100:g}%: {_secs(t.seconds)}, "
                f"{t.worker_seconds.estimate:.1f} worker-s{plan}"
            )
        if self.caveat:
            out.append(f"caveat: {self.caveat}")
        return out


def _secs(i: QuoteInterval) -> str:
    return f"{i.estimate:.1f} s ({i.low:.1f} to {i.high:.1f})"


#: The fields of ``Quote`` read from the server's answer, as paths into the schema, so the
#: drift test checks them too.
QUOTE_PATHS = (
    ("fleet",),
    ("workers",),
    ("frames",),
    ("spp",),
    ("black",),
    ("error_estimate_caveat",),
    ("quote", "planned", "seconds"),
    ("quote", "planned", "error"),
    ("quote", "targets", "target"),
    ("quote", "targets", "within_plan"),
    ("quote", "targets", "cost", "seconds"),
    ("quote", "targets", "cost", "worker_seconds"),
)
