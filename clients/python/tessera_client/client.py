"""A client of Tessera's HTTP API v1 (docs/api.md) on the standard library alone.

The server, token and CA file follow ``tessera submit``: ``TESSERA_SERVER`` (default
``http://127.0.0.1:8080``) and ``TESSERA_API_TOKEN`` where none is given, and a CA file
(PEM) that an ``https://`` server's certificate must be issued by.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import ssl
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Callable, Dict, List, Optional

from .models import FrameRange, JobSettings, JobStatus, Quote, SceneUploaded

#: Where the API lives under the server's URL.
API_PREFIX = "/api/v1"
#: The server when neither an argument nor ``TESSERA_SERVER`` names one.
DEFAULT_SERVER = "http://127.0.0.1:8080"


class TesseraError(Exception):
    """Anything that kept a request from being answered: its ``str`` is a message for a
    person, with no traceback needed."""


class TransportError(TesseraError):
    """The server could not be reached or answered something that is not the API (a
    refused connection, a TLS failure, a timeout, a proxy's page)."""


class ApiError(TesseraError):
    """The server refused the request: ``{"error": {"code", "message", "field"}}``."""

    def __init__(self, status: int, code: str, message: str, field: Optional[str] = None):
        self.status = status
        self.code = code
        self.message = message
        #: The input to blame (a body field as a dotted path, a query parameter or a
        #: header), when one is.
        self.field = field
        super().__init__(self.describe())

    def describe(self) -> str:
        """The error for a person: the field first when one is to blame."""
        where = f"{self.field}: " if self.field and not self.message.startswith(self.field) else ""
        hint = ""
        if self.code == "unauthorized":
            hint = " (check the API token: TESSERA_API_TOKEN or the add-on's preferences)"
        return f"{where}{self.message}{hint} [{self.status} {self.code}]"


#: The first bytes of an OpenEXR file.
_EXR_MAGIC = bytes([0x76, 0x2F, 0x31, 0x01])


def _is_colour(value: str) -> bool:
    """Whether ``value`` is ``R,G,B`` (three numbers) rather than a file name."""
    parts = value.split(",")
    if len(parts) != 3:
        return False
    try:
        [float(p) for p in parts]
    except ValueError:
        return False
    return True


def sha256_hex(data: bytes) -> str:
    """The name the coordinator gives an uploaded scene: its SHA-256 in lower-case hex."""
    return hashlib.sha256(data).hexdigest()


#: How the coordinator says that a job's ``scene`` hash names no uploaded scene
#: (crates/tessera-coordinator/src/service/scenes.rs): the client then uploads and retries.
_MISSING_SCENE = "no uploaded scene has hash"


class Client:
    """One coordinator's HTTP API v1.

    ``server`` is the coordinator's URL (``http://HOST:8080``; an ``/api/v1`` suffix is
    allowed); ``token`` its API token; ``ca_file`` a PEM file of CA certificates for an
    ``https://`` server. Unset, they come from ``TESSERA_SERVER``, ``TESSERA_API_TOKEN``
    and the default trust store, as with ``tessera submit``.
    """

    def __init__(
        self,
        server: Optional[str] = None,
        token: Optional[str] = None,
        ca_file: Optional[str] = None,
        timeout: float = 60.0,
    ):
        server = server or os.environ.get("TESSERA_SERVER") or DEFAULT_SERVER
        server = server.strip().rstrip("/")
        if server.endswith(API_PREFIX):
            server = server[: -len(API_PREFIX)]
        if not re.match(r"^https?://[^/]+", server):
            raise TesseraError(f"the server must be an http:// or https:// URL, not {server!r}")
        self.server = server
        self.token = token if token else (os.environ.get("TESSERA_API_TOKEN") or None)
        self.timeout = timeout
        self._ssl: Optional[ssl.SSLContext] = None
        if ca_file:
            if not server.startswith("https://"):
                raise TesseraError(f"a CA file ({ca_file}) needs an https:// server, not {server}")
            try:
                self._ssl = ssl.create_default_context(cafile=ca_file)
            except (OSError, ssl.SSLError) as e:
                raise TesseraError(f"the CA file {ca_file}: {e}") from None

    # ------------------------------------------------------------------ plumbing

    def dashboard_url(self, job_id: Optional[int] = None) -> str:
        """The dashboard's page of a job (or its front page)."""
        return f"{self.server}/" + (f"#/jobs/{job_id}" if job_id is not None else "")

    def _request(
        self,
        method: str,
        path: str,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        headers: Optional[Dict[str, str]] = None,
    ) -> bytes:
        url = self.server + API_PREFIX + path
        req = urllib.request.Request(url, data=body, method=method)
        if self.token:
            req.add_header("Authorization", f"Bearer {self.token}")
        if content_type:
            req.add_header("Content-Type", content_type)
        for k, v in (headers or {}).items():
            req.add_header(k, v)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout, context=self._ssl) as resp:
                return resp.read()
        except urllib.error.HTTPError as e:
            raw = e.read()
            try:
                err = json.loads(raw)["error"]
                raise ApiError(e.code, err["code"], err["message"], err.get("field")) from None
            except (ValueError, KeyError, TypeError):
                text = raw[:200].decode("utf-8", "replace").strip()
                raise TransportError(f"{url}: HTTP {e.code}: {text or e.reason}") from None
        except urllib.error.URLError as e:
            reason = e.reason
            if isinstance(reason, ssl.SSLError):
                raise TransportError(f"{self.server}: TLS: {reason}") from None
            raise TransportError(f"cannot reach {self.server}: {reason}") from None
        except (OSError, ValueError) as e:
            # Timeouts, resets and malformed URLs alike: a message, never a traceback.
            raise TransportError(f"{self.server}: {e}") from None

    def _json(self, method: str, path: str, payload=None, headers=None):
        body = None if payload is None else json.dumps(payload).encode()
        raw = self._request(method, path, body, "application/json" if body else None, headers)
        try:
            return json.loads(raw)
        except ValueError:
            raise TransportError(f"{self.server}{API_PREFIX}{path}: not JSON: {raw[:80]!r}") from None

    # ------------------------------------------------------------------ the API

    def openapi(self) -> Dict:
        """The server's OpenAPI document."""
        return self._json("GET", "/openapi.json")

    def upload_scene(self, data: bytes) -> SceneUploaded:
        """``POST /scenes``: uploads a ``.glb`` or self-contained ``.gltf``."""
        return SceneUploaded.from_json(
            self._json_raw("POST", "/scenes", data, "application/octet-stream")
        )

    def upload_environment(self, data: bytes) -> str:
        """``POST /scenes`` with an environment image (an equirectangular Radiance
        ``.hdr`` or OpenEXR file, which the coordinator decodes at upload); returns its
        hash, the ``environment.source`` of jobs it lights."""
        if not (data.startswith(b"#?") or data.startswith(_EXR_MAGIC)):
            raise TesseraError(
                "not a Radiance .hdr (#?RADIANCE) or OpenEXR file: an environment is an "
                "equirectangular HDR image"
            )
        up = self.upload_scene(data)
        if up.hash != sha256_hex(data):
            raise TesseraError(
                f"the coordinator named the image {up.hash}, not its SHA-256 {sha256_hex(data)}"
            )
        return up.hash

    def environment(
        self, source, strength: float = 1.0, rotation_degrees: float = 0.0
    ) -> Dict[str, object]:
        """The ``environment`` job setting: ``source`` is the bytes of an image (uploaded
        with :meth:`upload_environment`), a path to one, or a colour ``"R,G,B"`` /
        ``(r, g, b)`` of radiance in W/(m^2 sr); ``strength`` scales it and
        ``rotation_degrees`` turns an image about the up axis."""
        if isinstance(source, (tuple, list)):
            source = ",".join(repr(float(v)) for v in source)
        elif isinstance(source, str) and not _is_colour(source):
            try:
                with open(source, "rb") as f:
                    source = f.read()
            except OSError as e:
                raise TesseraError(f"reading environment {source}: {e.strerror or e}") from None
        if isinstance(source, (bytes, bytearray)):
            source = self.upload_environment(bytes(source))
        return {"source": source, "strength": float(strength), "rotation_degrees": float(rotation_degrees)}

    def _json_raw(self, method, path, body, content_type):
        raw = self._request(method, path, body, content_type)
        try:
            return json.loads(raw)
        except ValueError:
            raise TransportError(f"{self.server}{API_PREFIX}{path}: not JSON: {raw[:80]!r}") from None

    def submit(self, settings: JobSettings, idempotency_key: Optional[str] = None) -> JobStatus:
        """``POST /jobs``: queues the job."""
        headers = {"idempotency-key": idempotency_key} if idempotency_key else None
        return JobStatus.from_json(self._json("POST", "/jobs", settings.to_json(), headers))

    def quote(self, settings: JobSettings, workers: Optional[int] = None) -> Quote:
        """``POST /jobs?dry_run=true``: what the job would cost; nothing is queued."""
        q = "/jobs?dry_run=true" + (f"&workers={int(workers)}" if workers else "")
        return Quote.from_json(self._json("POST", q, settings.to_json()))

    def job(self, job_id: int) -> JobStatus:
        """``GET /jobs/{id}``."""
        return JobStatus.from_json(self._json("GET", f"/jobs/{int(job_id)}"))

    def jobs(self, limit: int = 50) -> List[JobStatus]:
        """``GET /jobs``: the newest ``limit`` jobs (1 to 200)."""
        d = self._json("GET", f"/jobs?limit={int(limit)}")
        return [JobStatus.from_json(j) for j in d["jobs"]]

    def cancel(self, job_id: int) -> JobStatus:
        """``DELETE /jobs/{id}``: cancels the job."""
        return JobStatus.from_json(self._json("DELETE", f"/jobs/{int(job_id)}"))

    def image(self, job_id: int, fmt: str = "exr", frame: Optional[int] = None) -> bytes:
        """``GET /jobs/{id}/image``: the image so far or the final one, as EXR or PNG."""
        if fmt not in ("exr", "png"):
            raise TesseraError(f"image format must be exr or png, not {fmt!r}")
        q = {"format": fmt}
        if frame is not None:
            q["frame"] = str(int(frame))
        return self._request("GET", f"/jobs/{int(job_id)}/image?{urllib.parse.urlencode(q)}")

    # ------------------------------------------------------------------ workflows

    def submit_scene(
        self,
        data: bytes,
        settings: JobSettings,
        idempotency_key: Optional[str] = None,
        on_upload: Optional[Callable[[SceneUploaded], None]] = None,
    ) -> JobStatus:
        """Submits a job of the scene ``data`` (``.glb`` bytes), content-addressed: the job
        names the scene by its SHA-256, and the bytes are uploaded only when the
        coordinator answers that it has no scene of that hash (the API has no separate
        "do you have it" call; the submission's own answer says so, naming ``scene``)."""
        settings.scene = sha256_hex(data)
        try:
            return self.submit(settings, idempotency_key)
        except ApiError as e:
            if not (e.field == "scene" and _MISSING_SCENE in e.message):
                raise
        up = self.upload_scene(data)
        if on_upload is not None:
            on_upload(up)
        if up.hash != settings.scene:
            raise TesseraError(
                f"the coordinator named the scene {up.hash}, not its SHA-256 {settings.scene}"
            )
        return self.submit(settings, idempotency_key)

    def quote_scene(
        self, data: bytes, settings: JobSettings, workers: Optional[int] = None
    ) -> Quote:
        """Quotes a job of the scene ``data``, uploading it first only if the coordinator
        does not have it (as :meth:`submit_scene`)."""
        settings.scene = sha256_hex(data)
        try:
            return self.quote(settings, workers)
        except ApiError as e:
            if not (e.field == "scene" and _MISSING_SCENE in e.message):
                raise
        self.upload_scene(data)
        return self.quote(settings, workers)

    def wait(
        self,
        job_id: int,
        on_progress: Optional[Callable[[JobStatus], None]] = None,
        every: float = 0.5,
        timeout: float = 86400.0,
    ) -> JobStatus:
        """Polls the job until it ends (done, failed or canceled) and returns its last
        status; ``on_progress`` sees each status polled. Raises :class:`TesseraError` after
        ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            st = self.job(job_id)
            if on_progress is not None:
                on_progress(st)
            if st.final:
                return st
            if time.monotonic() >= deadline:
                raise TesseraError(f"job {job_id} did not end within {timeout:g} s")
            time.sleep(every)

    def download_frames(
        self,
        job_id: int,
        pattern: str,
        frames: Optional[FrameRange] = None,
        fmt: Optional[str] = None,
    ) -> List[str]:
        """Writes each frame of the job to ``pattern`` with its run of ``#`` replaced by
        the frame number zero-padded to the run's length (``out_####.exr``), as
        ``tessera submit -o`` does; returns the paths written. ``frames`` defaults to the
        job's; the format follows the extension (``.png``, else EXR)."""
        if frames is None:
            frames = self.job(job_id).settings.frames
        fmt = fmt or ("png" if pattern.lower().endswith(".png") else "exr")
        if frames.count() > 1 and frame_pattern(pattern) is None:
            raise TesseraError(
                f"a job of {frames.count()} frames writes one file per frame: give the "
                f"output a run of # for the frame number, e.g. out_####.{fmt}"
            )
        written = []
        for f in range(frames.start, frames.end + 1):
            path = frame_path(pattern, f)
            data = self.image(job_id, fmt, f)
            d = os.path.dirname(path)
            if d:
                os.makedirs(d, exist_ok=True)
            with open(path, "wb") as out:
                out.write(data)
            written.append(path)
        return written


def frame_pattern(path: str):
    """The (start, end) of the last run of ``#`` in the file name of ``path``, if any."""
    head, name = os.path.split(path)
    end = name.rfind("#")
    if end < 0:
        return None
    start = end
    while start > 0 and name[start - 1] == "#":
        start -= 1
    off = len(path) - len(name)
    return off + start, off + end + 1


def frame_path(path: str, frame: int) -> str:
    """``path`` with its run of ``#`` replaced by ``frame`` zero-padded to the run's
    length (``out_####.exr``, 7: ``out_0007.exr``); without a run, ``path`` itself."""
    r = frame_pattern(path)
    if r is None:
        return path
    start, end = r
    return f"{path[:start]}{frame:0{end - start}d}{path[end:]}"
