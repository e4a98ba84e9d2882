"""Tessera's HTTP API v1 from Python: upload, submit, quote, status, wait, download, cancel.

    from tessera_client import Client, JobSettings
    c = Client()                      # TESSERA_SERVER, TESSERA_API_TOKEN
    job = c.submit_scene(open("shot.glb", "rb").read(), JobSettings(scene="", spp=256))
    c.wait(job.id, on_progress=lambda s: print(s.progress_line()))
    c.download_frames(job.id, "out_####.exr")

Standard library only, so it can be vendored (the Blender add-on does). Reference:
docs/clients.md.
"""

from .client import (
    API_PREFIX,
    DEFAULT_SERVER,
    ApiError,
    Client,
    TesseraError,
    TransportError,
    frame_path,
    frame_pattern,
    sha256_hex,
)
from .models import (
    ADAPTIVE_MODES,
    FINAL_STATES,
    JOB_STATES,
    FrameRange,
    JobSettings,
    JobStatus,
    Quote,
    QuoteInterval,
    QuoteTarget,
    SceneUploaded,
)

__version__ = "0.1.0"

__all__ = [
    "API_PREFIX",
    "DEFAULT_SERVER",
    "ADAPTIVE_MODES",
    "FINAL_STATES",
    "JOB_STATES",
    "ApiError",
    "Client",
    "FrameRange",
    "JobSettings",
    "JobStatus",
    "Quote",
    "QuoteInterval",
    "QuoteTarget",
    "SceneUploaded",
    "TesseraError",
    "TransportError",
    "frame_path",
    "frame_pattern",
    "sha256_hex",
]
