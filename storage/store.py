"""Versioned, write-once artifact store.

Layout: ``ROOT/<campaign>/<step>/v0001/`` holding the step's files and a ``manifest.json``::

    {"step", "campaign", "version", "created" (UTC ISO), "inputs", "inputs_hash",
     "code_version", "files": {relative path: {"sha256", "bytes"}}}

A version is written in a hidden temp dir inside the step folder and published with one atomic
``os.rename``, so readers never see a half-written version and a crash leaves at most a
``.tmp-*`` dir behind (ignored by every listing). Existing versions are never overwritten or
deleted. ``ROOT/<campaign>/campaign.json`` holds the settings the campaign's name is bound to
(:meth:`ArtifactStore.settings`, :meth:`ArtifactStore.bind_settings`).
``ROOT/<campaign>/evaluations/`` (and ``evaluations-<name>/``, a campaign's other
journals) is reserved for :class:`storage.EvaluationJournal`; ``ROOT/<campaign>/runs/`` and
``diagnosis-runs/`` hold the simulator's run directories (:meth:`ArtifactStore.work_dir`).

The store never leaves its root: campaign and step names are checked before use (no ``/``,
no ``..``), and no symbolic link below the root is followed for writing (a linked campaign or
step folder is refused with :class:`LinkRefusedError`); the root itself may be a link.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import os
import re
import shutil
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path, PurePosixPath
from typing import Any, Union

import pandas as pd

from .jsonable import sha256_json, to_jsonable

MANIFEST = "manifest.json"
JOURNAL_STEP = "evaluations"
RUNS = "runs"
"""Folder of a campaign's run directories, one per call (``runs/<index:06d>``)."""
DIAGNOSIS_RUNS = "diagnosis-runs"
"""Folder of a diagnosis's run directories, one per run (``diagnosis-runs/<step>-<n:05d>``)."""
SETTINGS = "campaign.json"
"""A campaign's settings: the ones its name is bound to, written once when it starts."""
NAME_RULE = "1-128 characters among letters, digits, '-', '_' and '.', not starting with '.'"
_NAME_RE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,127}")
_VERSION_RE = re.compile(r"v(\d{4,})")
_MAX_PUBLISH_ATTEMPTS = 1000

FileContent = Union[bytes, str, pd.DataFrame, Mapping[str, Any]]


class LinkRefusedError(ValueError):
    """A folder the store would write into is a symbolic link (it could lead outside the root)."""


def refuse_links(root: Path, *names: str) -> Path:
    """``root/names...`` after checking that no existing part below ``root`` is a symbolic link
    (nor anything but a folder); LinkRefusedError naming the part otherwise."""
    path = Path(root)
    for name in names:
        path = path / name
        if path.is_symlink():
            raise LinkRefusedError(f"{path} is a symbolic link (to {os.readlink(path)}); the "
                                   f"artifact store never writes through a link, which could "
                                   f"lead outside {root}. Replace it by a real folder")
        if path.exists() and not path.is_dir():
            raise LinkRefusedError(f"{path} is not a folder; the artifact store needs a folder "
                                   "there. Move the file away")
    return path


def journal_folder(name: str | None = None) -> str:
    """The folder of a campaign's journal: ``evaluations`` for its calls (``name`` None), else
    ``evaluations-<name>`` for another journal of the campaign (e.g. a diagnosis's runs)."""
    if name is None:
        return JOURNAL_STEP
    return validate_name("journal", f"{JOURNAL_STEP}-{validate_name('journal', name)}")


def is_journal_folder(step: str) -> bool:
    """Whether ``step`` names a journal's folder (see :func:`journal_folder`)."""
    return step == JOURNAL_STEP or step.startswith(f"{JOURNAL_STEP}-")


def validate_name(kind: str, value: object) -> str:
    """Return ``value`` if it is a valid campaign/step name; else ValueError stating the rule."""
    if isinstance(value, str) and _NAME_RE.fullmatch(value):
        return value
    raise ValueError(f"invalid {kind} name {value!r}: a {kind} name must be {NAME_RULE}")


@dataclass(frozen=True)
class ArtifactVersion:
    """One published version of a step. ``reused`` is True when :meth:`ArtifactStore.put`
    returned an existing version instead of writing a new one (or :meth:`ArtifactStore.reusable`
    found it)."""

    campaign: str
    step: str
    version: int
    path: Path
    manifest: dict[str, Any] = field(compare=False, repr=False)
    reused: bool = field(default=False, compare=False)

    @property
    def files(self) -> list[str]:
        """Relative paths of the files listed in the manifest."""
        files = self.manifest.get("files")
        return sorted(files) if isinstance(files, dict) else []

    def file(self, name: str) -> Path:
        """Path of file ``name`` (a relative path listed in the manifest)."""
        if name not in self.files:
            raise FileNotFoundError(f"{name!r} is not a file of {self.campaign}/{self.step} "
                                    f"v{self.version:04d}; it has {self.files}")
        return self.path / _relative_path(name)

    def read_parquet(self, name: str) -> pd.DataFrame:
        """Read Parquet file ``name`` into a DataFrame."""
        return pd.read_parquet(self.file(name), engine="pyarrow")

    def read_json(self, name: str) -> Any:
        """Read JSON file ``name`` (a dict for JSON written by :meth:`ArtifactStore.put_files`)."""
        return json.loads(self.file(name).read_text(encoding="utf-8"))

    def ref(self) -> dict[str, Any]:
        """A small JSON-able reference to this version, to put in a downstream step's inputs.

        It includes a hash of the file hashes, so the downstream step is redone when the upstream
        content differs even under the same version number (e.g. after the store was rebuilt).
        """
        return {"campaign": self.campaign, "step": self.step, "version": self.version,
                "content_hash": sha256_json(self.manifest.get("files", {}))}

    def verify(self) -> list[str]:
        """Problems with this version on disk (empty when intact): unreadable manifest, missing
        files, size/hash mismatches, files not in the manifest."""
        files = self.manifest.get("files")
        if not isinstance(files, dict):
            return [f"{self.path / MANIFEST}: manifest missing, unreadable or without 'files'"]
        problems = [f"manifest {key} is {self.manifest.get(key)!r}, expected {expected!r}"
                    for key, expected in (("campaign", self.campaign), ("step", self.step),
                                          ("version", self.version))
                    if self.manifest.get(key) != expected]
        for name, meta in sorted(files.items()):
            try:
                path = self.path / _relative_path(name)
            except ValueError as exc:
                problems.append(str(exc))
                continue
            if not path.is_file():
                problems.append(f"missing file: {name}")
                continue
            digest, size = _file_digest(path)
            expected = (meta.get("sha256"), meta.get("bytes")) if isinstance(meta, dict) else None
            if expected != (digest, size):
                problems.append(f"hash mismatch: {name} (manifest {meta}, "
                                f"on disk sha256 {digest}, {size} bytes)")
        try:
            extra = sorted(set(_tree(self.path)) - set(files) - {MANIFEST})
        except ValueError as exc:
            return problems + [str(exc)]
        return problems + [f"file not in manifest: {name}" for name in extra]


class ArtifactStore:
    """Versioned artifacts under ``root``: ``root/<campaign>/<step>/vNNNN/``."""

    def __init__(self, root: Path | str):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"ArtifactStore({str(self.root)!r})"

    def put(self, campaign: str, step: str, inputs: Mapping[str, Any],
            writer: Callable[[Path], None], code_version: str) -> ArtifactVersion:
        """Publish a new version of ``campaign/step``, or reuse the latest one.

        If :meth:`reusable` finds a version for ``inputs`` and ``code_version``, it is
        returned with ``reused=True`` and ``writer`` is not called: ``inputs`` must therefore
        name everything that determines the files (parameters, config, upstream
        ``ref()``s...). Otherwise ``writer(tmp_dir)`` writes regular files into a fresh temp
        dir (``manifest.json`` at its top is reserved), which is hashed and atomically renamed
        to the next ``vNNNN``; a version number taken concurrently is skipped. If the writer
        raises, the temp dir is removed and the exception propagates.
        """
        reused = self.reusable(campaign, step, inputs, code_version)  # checks the arguments
        if reused is not None:
            return reused
        step_dir = self._step_dir(campaign, step)
        inputs = to_jsonable(inputs, "inputs")
        inputs_hash = sha256_json(inputs)
        step_dir.mkdir(parents=True, exist_ok=True)
        tmp = step_dir / f".tmp-{uuid.uuid4().hex}"
        tmp.mkdir()  # not tempfile.mkdtemp: its 0o700 mode would stick to the published version
        try:
            writer(tmp)
            files = {}
            for name in _tree(tmp):
                if name == MANIFEST:
                    raise ValueError(f"the writer created {MANIFEST}, which is reserved for the "
                                     f"store; use another file name")
                digest, size = _file_digest(tmp / name)
                files[name] = {"sha256": digest, "bytes": size}
            manifest = {"step": step, "campaign": campaign, "version": 0,
                        "created": datetime.now(timezone.utc).isoformat(),
                        "inputs": inputs, "inputs_hash": inputs_hash,
                        "code_version": code_version, "files": files}
            return self._publish(tmp, step_dir, manifest)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def reusable(self, campaign: str, step: str, inputs: Mapping[str, Any],
                 code_version: str) -> ArtifactVersion | None:
        """The version :meth:`put` returns for these arguments instead of writing one: the
        latest version of ``campaign/step`` when it has the same inputs (by ``inputs_hash``)
        and ``code_version`` and verifies intact, with ``reused=True``; None when ``put`` would
        write a new version. Lets a caller whose files are costly to make look first. The
        arguments are checked as ``put`` checks them (names, reserved steps, inputs, links)."""
        self._step_dir(campaign, step)
        if step == JOURNAL_STEP:
            raise ValueError(f"step name {JOURNAL_STEP!r} is reserved for the evaluation journal")
        if is_journal_folder(step):
            raise ValueError(f"step name {step!r} is reserved for a journal (names starting "
                             f"with {JOURNAL_STEP}-)")
        if not isinstance(inputs, Mapping):
            raise TypeError(f"inputs must be a dict, got {type(inputs).__name__}")
        if not isinstance(code_version, str) or not code_version:
            raise ValueError(f"code_version must be a non-empty string, got {code_version!r}")
        inputs_hash = sha256_json(to_jsonable(inputs, "inputs"))
        refuse_links(self.root, campaign, step)
        latest = self.latest(campaign, step)
        if (latest is not None and latest.manifest.get("inputs_hash") == inputs_hash
                and latest.manifest.get("code_version") == code_version and not latest.verify()):
            return dataclasses.replace(latest, reused=True)
        return None

    def put_files(self, campaign: str, step: str, inputs: Mapping[str, Any],
                  files: Mapping[str, FileContent], code_version: str) -> ArtifactVersion:
        """:meth:`put` with files given as ``{relative path: content}``.

        Content: ``bytes`` as is, ``str`` as UTF-8 text, ``pandas.DataFrame`` as Parquet
        (pyarrow, index kept), ``dict`` as indented JSON (see :mod:`storage.jsonable`: NaN and
        inf are stored as null). Names are relative POSIX paths (``sub/dir/name.ext``).
        """
        payloads: dict[str, bytes | pd.DataFrame] = {}
        for name, content in files.items():
            if _relative_path(name).as_posix() == MANIFEST:
                raise ValueError(f"{MANIFEST} is reserved for the store; use another file name")
            if isinstance(content, (bytes, bytearray, memoryview)):
                payloads[name] = bytes(content)
            elif isinstance(content, str):
                payloads[name] = content.encode("utf-8")
            elif isinstance(content, pd.DataFrame):
                payloads[name] = content
            elif isinstance(content, Mapping):
                text = json.dumps(to_jsonable(content, name), indent=2, sort_keys=True,
                                  ensure_ascii=False, allow_nan=False)
                payloads[name] = (text + "\n").encode("utf-8")
            else:
                raise TypeError(f"file {name!r}: content must be bytes, str, DataFrame or dict, "
                                f"got {type(content).__name__}")

        def writer(directory: Path) -> None:
            for name, payload in payloads.items():
                path = directory / _relative_path(name)
                path.parent.mkdir(parents=True, exist_ok=True)
                if isinstance(payload, pd.DataFrame):
                    payload.to_parquet(path, engine="pyarrow")
                else:
                    path.write_bytes(payload)

        return self.put(campaign, step, inputs, writer, code_version)

    def latest(self, campaign: str, step: str) -> ArtifactVersion | None:
        """The highest-numbered version of ``campaign/step``, or None if there is none."""
        numbers = self._version_numbers(self._step_dir(campaign, step))
        return self.get(campaign, step, max(numbers)) if numbers else None

    def versions(self, campaign: str, step: str) -> list[ArtifactVersion]:
        """All versions of ``campaign/step``, oldest first."""
        numbers = self._version_numbers(self._step_dir(campaign, step))
        return [self.get(campaign, step, n) for n in sorted(numbers)]

    def get(self, campaign: str, step: str, version: int) -> ArtifactVersion:
        """Version ``version`` of ``campaign/step``; LookupError if it does not exist.

        A version whose manifest cannot be read is still returned (with an empty manifest) so
        that :meth:`ArtifactVersion.verify` can report it.
        """
        path = self._step_dir(campaign, step) / _version_dirname(version)
        if not path.is_dir():
            raise LookupError(f"no version {version} of {campaign}/{step} in {self.root}")
        try:
            manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            manifest = {}
        if not isinstance(manifest, dict):
            manifest = {}
        return ArtifactVersion(campaign, step, version, path, manifest)

    def campaigns(self) -> list[str]:
        """Names of the campaigns in the store, sorted."""
        return _subdirs(self.root)

    def steps(self, campaign: str) -> list[str]:
        """Names of the steps of ``campaign`` that have at least one version, sorted."""
        campaign_dir = self.root / validate_name("campaign", campaign)
        return [s for s in _subdirs(campaign_dir)
                if not is_journal_folder(s) and self._version_numbers(campaign_dir / s)]

    def has_campaign(self, campaign: str) -> bool:
        """Whether ``campaign`` has a folder in the store (anything stored under its name)."""
        return (self.root / validate_name("campaign", campaign)).is_dir()

    def require_campaign(self, campaign: str) -> None:
        """Raise ``FileNotFoundError`` (ENOENT, naming the missing folder) when ``campaign``
        has no folder in the store: where its steps ran moments before, the store was removed
        while a command ran, a fault of its file system (:mod:`storage.space`), not a result
        that was never made."""
        if not self.has_campaign(campaign):
            raise FileNotFoundError(errno.ENOENT, "no such folder", str(self.root / campaign))

    def settings(self, campaign: str) -> dict[str, Any] | None:
        """The settings ``campaign``'s name is bound to (its ``campaign.json``); None when it
        has none yet."""
        path = self.root / validate_name("campaign", campaign) / SETTINGS
        if not path.is_file():
            return None
        return json.loads(path.read_text(encoding="utf-8"))

    def bind_settings(self, campaign: str, settings: Mapping[str, Any]) -> Path:
        """Bind ``campaign``'s name to ``settings``: written once, atomically (a temp file,
        fsync'd, renamed into place). The same settings again are a no-op; other settings
        raise ValueError naming the campaign (compare first: see ``flows.campaign``)."""
        directory = refuse_links(self.root, validate_name("campaign", campaign))
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / SETTINGS
        data = to_jsonable(dict(settings), f"{campaign}/{SETTINGS}")
        if path.is_file():
            if sha256_json(json.loads(path.read_text(encoding="utf-8"))) != sha256_json(data):
                raise ValueError(f"campaign '{campaign}' in {self.root} is bound to other "
                                 f"settings ({path}); choose another campaign name")
            return path
        tmp = directory / f".{SETTINGS}.{uuid.uuid4().hex}.tmp"
        try:
            _write_json(tmp, data)
            os.replace(tmp, path)
        except BaseException:  # a full disk: no half-written file left behind
            tmp.unlink(missing_ok=True)
            raise
        return path

    def work_dir(self, campaign: str, folder: str) -> Path:
        """``ROOT/<campaign>/<folder>``, a folder of files that are no artifact version (the
        simulator's run directories: :data:`RUNS`, :data:`DIAGNOSIS_RUNS`); names checked, not
        created."""
        return self.root / validate_name("campaign", campaign) / validate_name("folder", folder)

    def _step_dir(self, campaign: str, step: str) -> Path:
        return self.root / validate_name("campaign", campaign) / validate_name("step", step)

    @staticmethod
    def _version_numbers(step_dir: Path) -> list[int]:
        try:
            names = os.listdir(step_dir)
        except (FileNotFoundError, NotADirectoryError):
            return []
        return [int(m.group(1)) for m in map(_VERSION_RE.fullmatch, names) if m]

    def _publish(self, tmp: Path, step_dir: Path, manifest: dict[str, Any]) -> ArtifactVersion:
        for _ in range(_MAX_PUBLISH_ATTEMPTS):
            number = max(self._version_numbers(step_dir), default=0) + 1
            manifest["version"] = number
            _write_json(tmp / MANIFEST, manifest)
            target = step_dir / _version_dirname(number)
            try:
                os.rename(tmp, target)  # fails on an existing, non-empty version dir
            except OSError as exc:
                if target.exists() or exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
                    continue  # another writer took this number: try the next one
                raise
            return ArtifactVersion(manifest["campaign"], manifest["step"], number, target,
                                   manifest)
        raise RuntimeError(f"could not publish a version in {step_dir} after "
                           f"{_MAX_PUBLISH_ATTEMPTS} attempts")


def _version_dirname(version: int) -> str:
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise ValueError(f"version must be an integer >= 1, got {version!r}")
    return f"v{version:04d}"


def _relative_path(name: str) -> PurePosixPath:
    path = PurePosixPath(name) if isinstance(name, str) else None
    if (path is None or not name or "\\" in name or path.is_absolute()
            or any(part in ("", ".", "..") for part in name.split("/"))):
        raise ValueError(f"invalid artifact file name {name!r}: use a relative POSIX path "
                         f"like 'tables/summary.parquet' without '.', '..' or '\\'")
    return path


def _tree(root: Path) -> list[str]:
    """Relative POSIX paths of the regular files under ``root``; ValueError on links/specials."""
    names = []
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath, name)
            if path.is_symlink() or not (path.is_dir() or path.is_file()):
                raise ValueError(f"{path}: artifacts must be regular files and folders, "
                                 f"not links or special files")
        names += [Path(dirpath, f).relative_to(root).as_posix() for f in filenames]
    return sorted(names)


def _file_digest(path: Path) -> tuple[str, int]:
    digest, size = hashlib.sha256(), 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
            size += len(chunk)
    return digest.hexdigest(), size


def _write_json(path: Path, data: Any) -> None:
    text = json.dumps(data, indent=2, ensure_ascii=False, allow_nan=False) + "\n"
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def _subdirs(directory: Path) -> list[str]:
    try:
        entries = list(os.scandir(directory))
    except (FileNotFoundError, NotADirectoryError):
        return []
    return sorted(e.name for e in entries
                  if _NAME_RE.fullmatch(e.name) and e.is_dir(follow_symlinks=False))
