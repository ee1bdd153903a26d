"""Self-describing HDF5 shards of simulated images.

A *shard* is one HDF5 file holding ``N`` simulated images and everything needed to
reproduce them (layout version :data:`FORMAT_VERSION`)::

    images                  (N, H, W) float32, chunked per image, gzip + shuffle (as
                            every other non-empty dataset)
    params/<name>           (N,) per-image (macro) parameters of
    subslope.simulation.macro.sample_macro:
                            float64 or int64; always theta_e, lens_x, lens_y, set_index,
                            plus gamma_sub (the label γ) in labelled scenes and
                            c_multiplier in CDM scenes
    params/noise_seed       (N,) uint64, torch seed of each image's noise
    sources/<field>         (N,) per image, COSMOS scenes: ident, z_phot, pixel_scale
                            (arcsec, at z_source), [mag]
    subhalos/<field>        flat arrays of all subhalos, image by image, heaviest first:
                            the drawn fields only, at the precision they were drawn at
                            (mass, c200 float32; x, y, gamma, e1, e2 float16; see
                            subslope.simulation.precision); the lens parameters (EPL
                            amplitude, NFW r_s, alpha_rs, r_t) are derived on reading
    subhalos/counts         (N,) int64 subhalos per image
    los/<field>, los/counts the same for line-of-sight halos, every field float32
    psf                     (k, k) float64 PSF kernel used for the convolution

File attributes: ``format`` (:data:`FORMAT_NAME`), ``format_version``, ``scene``,
``scene_spec`` (JSON of the resolved scene), ``config_hash`` (SHA-256 of the canonical
JSON of the config sections that affect the images), ``config`` (JSON of those
sections), ``seed_entropy`` and ``seed_spawn_key`` (the numpy SeedSequence of the
shard), ``package_version``, ``n_images``, ``render_settings`` (JSON),
``subhalo_profile`` / ``los_profile`` and, written last, ``complete = True``.

Every dataset carries HDF5's Fletcher-32 checksum (per chunk, so per image for
``images``), verified by HDF5 on every read: a corrupted byte anywhere (an image, a label)
fails the read that touches it, and :class:`CheckedRows` turns that failure into a
:class:`ShardError` naming the file, the dataset and the first bad row.

Writing is atomic (:func:`subslope.io.atomic.atomic_write`: a temporary file beside the
shard, renamed once complete); an existing shard is never overwritten unless asked. No time stamps
are stored (``track_times=False``), so the same inputs give a byte-identical file.
:func:`open_shard` checks format, version, completeness and the required datasets and
raises :class:`ShardError` naming the file otherwise.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from subslope.config import canonical_json, config_hash
from subslope.io.atomic import atomic_write
from subslope.ragged import counts_to_offsets

__all__ = [
    "WORKFLOW_SHARD_FOLDER",
    "placement_problem",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "REQUIRED_DATASETS",
    "LIGHT_FIT_GROUP",
    "ShardError",
    "CheckedRows",
    "open_hdf5",
    "verify_shard",
    "Shard",
    "write_shard",
    "with_light_fit",
    "open_shard",
    "canonical_json",
    "config_hash",
    "file_sha256",
]

FORMAT_NAME = "subslope-shard"
FORMAT_VERSION = 3

#: Group of the optional per-image lens-light fit (``simulation.light_fit``).
LIGHT_FIT_GROUP = "light_fit"

#: Datasets every shard has (the estimator relies on these names).
REQUIRED_DATASETS = (
    "images",
    "params/theta_e",
    "params/lens_x",
    "params/lens_y",
    "params/set_index",
    "params/noise_seed",
    "subhalos/counts",
    "los/counts",
    "psf",
)


class ShardError(ValueError):
    """A shard file is missing, partial, corrupt or not a subslope shard."""


def file_sha256(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def _attr_value(value: Any) -> Any:
    if isinstance(value, (dict, list, tuple)):
        return canonical_json(value)
    if value is None:
        return "null"
    return value


def _dataset(group: h5py.Group, name: str, data: np.ndarray, **kwargs) -> None:
    data = np.asarray(data)
    if data.dtype.kind == "f" and data.dtype not in (np.float16, np.float32):
        data = data.astype(np.float64)
    elif data.dtype.kind in "iu" and data.dtype not in (np.uint64,):
        data = data.astype(np.int64)
    elif data.dtype.kind == "b":
        data = data.astype(np.int8)
    if not data.size:
        kwargs = {}
    group.create_dataset(name, data=data, track_times=False, fletcher32=data.size > 0, **kwargs)


def write_shard(
    path: str | os.PathLike[str],
    *,
    images: np.ndarray,
    params: Mapping[str, np.ndarray],
    psf: np.ndarray,
    subhalos: Mapping[str, np.ndarray],
    los: Mapping[str, np.ndarray],
    sources: Mapping[str, np.ndarray] | None = None,
    light_fit: Mapping[str, np.ndarray] | None = None,
    attrs: Mapping[str, Any],
    overwrite: bool = False,
    compression: str | None = "gzip",
) -> Path:
    """Write one shard atomically and return its path.

    Parameters
    ----------
    images : (N, H, W) array, stored as float32.
    params : per-image arrays of length N; must include the names of
        :data:`REQUIRED_DATASETS` under ``params/``.
    psf : 2-D PSF kernel.
    subhalos, los : flat arrays plus ``counts`` (N,); keys become ``<group>/<key>``.
    sources : per-image source arrays (COSMOS scenes) or None.
    light_fit : per-image lens-light fit parameters (group :data:`LIGHT_FIT_GROUP`,
        :mod:`subslope.physics.light.subtract`) or None.
    attrs : file attributes (dicts/lists are stored as canonical JSON strings); the
        format attributes, ``n_images`` and ``complete`` are added here.
    overwrite : replace an existing file (default: refuse with :class:`FileExistsError`).
    compression : 'gzip' (level 4, with shuffle), 'lzf' or None.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"shard {path} already exists; delete it or pass overwrite=True")
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 3:
        raise ShardError(f"{path}: images must have shape (N, H, W), got {images.shape}")
    n, h, w = images.shape
    _check_arrays(path, n, params, sources, subhalos, los)
    for key, values in (light_fit or {}).items():
        if np.shape(values) != (n,):
            raise ShardError(f"{path}: {LIGHT_FIT_GROUP}/{key} must have shape ({n},)")

    comp: dict[str, Any] = {}
    if compression == "gzip":
        comp = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    elif compression == "lzf":
        comp = {"compression": "lzf", "shuffle": True}
    elif compression is not None:
        raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")

    with atomic_write(path) as tmp, h5py.File(tmp, "w", track_order=False) as f:
        chunks = (1, h, w) if n else None
        f.create_dataset(
            "images",
            data=images,
            chunks=chunks,
            track_times=False,
            fletcher32=bool(n),
            **(comp if n else {}),
        )
        _dataset(f, "psf", np.asarray(psf, dtype=np.float64))
        for group, arrays in (
            ("params", params),
            ("sources", sources or {}),
            ("subhalos", subhalos),
            ("los", los),
        ) + (((LIGHT_FIT_GROUP, light_fit),) if light_fit is not None else ()):
            g = f.create_group(group, track_order=False)
            for key in sorted(arrays):
                _dataset(g, key, arrays[key], **comp)
        meta = dict(attrs)
        meta.update(format=FORMAT_NAME, format_version=FORMAT_VERSION, n_images=n)
        for key in sorted(meta):
            f.attrs[key] = _attr_value(meta[key])
        f.attrs["complete"] = True  # last: marks a finished file
    return path


def with_light_fit(
    src: str | os.PathLike[str], dst: str | os.PathLike[str], light_fit: Mapping[str, np.ndarray]
) -> Path:
    """Write ``dst`` atomically: the shard ``src`` with the lens-light fit ``light_fit``
    (arrays ``(N,)``, group :data:`LIGHT_FIT_GROUP`) added or replaced; its images and
    every other dataset are copied unchanged."""
    dst = Path(dst)
    with h5py.File(src, "r") as f:
        n = int(f["images"].shape[0])
        if not f.attrs.get("complete", False):
            raise ShardError(f"{src}: incomplete shard (no 'complete' attribute)")
        for key, values in light_fit.items():
            if np.shape(values) != (n,):
                raise ShardError(f"{src}: {LIGHT_FIT_GROUP}/{key} must have shape ({n},)")
        with atomic_write(dst) as tmp, h5py.File(tmp, "w", track_order=False) as out:
            for name in f:
                if name != LIGHT_FIT_GROUP:
                    f.copy(f[name], out, name=name)
            g = out.create_group(LIGHT_FIT_GROUP, track_order=False)
            for key in sorted(light_fit):
                _dataset(g, key, light_fit[key])
            for key in sorted(f.attrs):
                out.attrs[key] = f.attrs[key]
    return dst


def _check_arrays(path, n: int, params, sources, subhalos, los) -> None:
    """Shapes of a shard's arrays: per-image groups ``(n,)``, populations flat with ``(n,)``
    counts, every required parameter present."""
    for group, arrays, per_image in (("params", params, True), ("sources", sources or {}, True)):
        for key, value in arrays.items():
            if per_image and np.shape(value) != (n,):
                raise ShardError(
                    f"{path}: {group}/{key} has shape {np.shape(value)}, expected ({n},)"
                )
    for group, arrays in (("subhalos", subhalos), ("los", los)):
        counts = np.asarray(arrays.get("counts"))
        if counts.shape != (n,):
            raise ShardError(f"{path}: {group}/counts must have shape ({n},), got {counts.shape}")
        total = int(counts.sum())
        for key, value in arrays.items():
            if key != "counts" and np.shape(value) != (total,):
                raise ShardError(
                    f"{path}: {group}/{key} has {np.shape(value)} entries, counts sum to {total}"
                )
    missing = [
        d for d in REQUIRED_DATASETS if d.startswith("params/") and d.split("/")[1] not in params
    ]
    if missing:
        raise ShardError(f"{path}: missing required parameter(s) {missing}")


def _recovery(path) -> str:
    return (
        f"delete {path} and run snakemake again to simulate it anew (the same seed gives "
        "the same shard), or restore that very shard (same scene, index and multiplier) "
        "from a copy"
    )


#: The folder under which the workflow keeps its shards as
#: ``<scene>/[a<multiplier>/]shard_<index>.h5`` (:func:`subslope.plan.shard_path`).
WORKFLOW_SHARD_FOLDER = "simulate_shard"


def placement_problem(path: Path, attrs: Mapping[str, Any]) -> str | None:
    """Why a shard at ``path`` inside :data:`WORKFLOW_SHARD_FOLDER` is not the shard its
    path names (scene, index, multiplier against its attributes), or None; shards kept
    elsewhere are not checked."""
    if WORKFLOW_SHARD_FOLDER not in path.parts[:-1] or not path.name.startswith("shard_"):
        return None
    index, folder = path.stem.removeprefix("shard_"), path.parent
    want: dict[str, Any] = {"shard_index": index}
    if folder.name.startswith("a") and folder.parent.name != WORKFLOW_SHARD_FOLDER:
        want["multiplier"], folder = folder.name[1:], folder.parent
    want["scene"] = folder.name
    have = {
        "scene": attrs.get("scene"),
        "shard_index": str(attrs.get("shard_index")),
        "multiplier": None if attrs.get("multiplier") is None else f"{attrs['multiplier']:g}",
    }
    wrong = [
        f"{k} {have[k]!r} (its path: {v!r})" for k, v in want.items() if k in attrs and have[k] != v
    ]
    if not wrong:
        return None
    return (
        f"{path} is not the shard its path names: it holds {', '.join(wrong)}; a shard "
        f"copied over another is refused. {_recovery(path)[0].upper()}{_recovery(path)[1:]}"
    )


def open_hdf5(path: str | os.PathLike[str]) -> h5py.File:
    """``h5py.File(path, "r")``; a missing, truncated or corrupt file raises
    :class:`ShardError` naming it (HDF5's own message does not) and how to recover."""
    if not Path(path).is_file():
        raise ShardError(f"shard file not found: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ShardError(
            f"{path} is not a readable HDF5 file (truncated or corrupt: {exc}); {_recovery(path)}"
        ) from None


class CheckedRows:
    """Reads of one dataset of a shard that name the file, the dataset and the first row
    that cannot be read (a checksum mismatch or a truncated file) in a :class:`ShardError`,
    instead of HDF5's bare "filter returned failure during read". Slice it like the
    dataset (``rows[lo:hi]``, ``rows[k]``, ``rows[...]``)."""

    def __init__(self, path: str | os.PathLike[str], dataset: h5py.Dataset):
        self.path = Path(path)
        self.dataset = dataset

    @property
    def shape(self) -> tuple[int, ...]:
        return self.dataset.shape

    @property
    def dtype(self) -> np.dtype:
        return self.dataset.dtype

    def __len__(self) -> int:
        return self.dataset.shape[0]

    def __getattr__(self, name: str):  # chunks, compression, attrs, ...: the dataset's
        if name == "dataset":
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, key):
        try:
            return self.dataset[key]
        except OSError as exc:
            raise ShardError(self._message(key, exc)) from None

    def _message(self, key, exc: OSError) -> str:
        name = self.dataset.name.lstrip("/")
        rows = range(len(self)) if self.dataset.shape else range(0)
        if isinstance(key, slice):
            rows = rows[key]
        elif isinstance(key, (int, np.integer)):
            rows = rows[int(key) : int(key) + 1]
        for k in rows:
            try:
                self.dataset[k]
            except OSError:
                what = "image" if name == "images" else "row"
                return (
                    f"{self.path}: {name} {what} {k} cannot be read ({exc}): the file is "
                    f"corrupt; {_recovery(self.path)}"
                )
        return f"{self.path}: dataset {name} cannot be read ({exc}); {_recovery(self.path)}"


class Shard:
    """A validated, read-only shard. Use as a context manager or call :meth:`close`.

    ``attrs`` holds the file attributes with JSON strings decoded; ``params``,
    ``sources``, ``subhalos``, ``los`` are dicts of numpy arrays (read on first use).
    """

    def __init__(self, path: Path, handle: h5py.File):
        self.path = path
        self.file = handle
        self.attrs = {k: _decode(v) for k, v in handle.attrs.items()}
        self._cache: dict[str, dict[str, np.ndarray]] = {}

    def __enter__(self) -> Shard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.file.close()

    def __len__(self) -> int:
        return int(self.attrs["n_images"])

    @property
    def images(self) -> CheckedRows:
        """The ``images`` dataset (N, H, W) float32 (read slices of it)."""
        return CheckedRows(self.path, self.file["images"])

    @property
    def psf(self) -> np.ndarray:
        return CheckedRows(self.path, self.file["psf"])[()]

    def group(self, name: str) -> dict[str, np.ndarray]:
        if name not in self._cache:
            g = self.file.get(name)
            self._cache[name] = (
                {} if g is None else {k: CheckedRows(self.path, g[k])[()] for k in g}
            )
        return self._cache[name]

    @property
    def params(self) -> dict[str, np.ndarray]:
        return self.group("params")

    @property
    def sources(self) -> dict[str, np.ndarray]:
        return self.group("sources")

    @property
    def subhalos(self) -> dict[str, np.ndarray]:
        return self.group("subhalos")

    @property
    def los(self) -> dict[str, np.ndarray]:
        return self.group("los")

    def ragged(self, name: str, index) -> dict[str, np.ndarray]:
        """Arrays of group ``subhalos`` or ``los`` restricted to images ``index``
        (an int, a slice or an index array); ``counts`` per selected image."""
        arrays = self.group(name)
        counts = arrays["counts"]
        off = counts_to_offsets(np.asarray(counts))
        sel = np.atleast_1d(np.arange(counts.size)[index])
        pick = (
            np.concatenate([np.arange(off[i], off[i + 1]) for i in sel])
            if sel.size
            else np.zeros(0, np.int64)
        )
        out = {k: v[pick] for k, v in arrays.items() if k != "counts"}
        out["counts"] = counts[sel]
        return out


def _decode(value: Any) -> Any:
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and (value[:1] in ("{", "[") or value == "null"):
        try:
            return json.loads(value)
        except (TypeError, json.JSONDecodeError):
            return value
    if isinstance(value, np.generic):
        return value.item()
    return value


def open_shard(path: str | os.PathLike[str]) -> Shard:
    """Open and validate a shard; raises :class:`ShardError` naming the file.

    Checks: readable HDF5, ``format`` and ``format_version``, ``complete`` written,
    the datasets of :data:`REQUIRED_DATASETS` present with ``n_images`` rows, and in the
    workflow's shard folder the scene, index and multiplier its path names
    (:func:`placement_problem`).
    """
    path = Path(path)
    handle = open_hdf5(path)
    try:
        fmt = _decode(handle.attrs.get("format"))
        if fmt != FORMAT_NAME:
            raise ShardError(
                f"{path} is not a subslope shard (format attribute {fmt!r}, expected "
                f"{FORMAT_NAME!r})"
            )
        version = _decode(handle.attrs.get("format_version"))
        if version != FORMAT_VERSION:
            raise ShardError(
                f"{path} has shard format version {version!r}; this subslope reads version "
                f"{FORMAT_VERSION} (version 2 added per-chunk checksums, version 3 stores the "
                f"halo populations at the precision they are drawn at); {_recovery(path)}"
            )
        if not bool(handle.attrs.get("complete", False)):
            raise ShardError(
                f"{path} is incomplete (no 'complete' attribute): the writer did not finish"
            )
        n = int(handle.attrs["n_images"])
        missing = [d for d in REQUIRED_DATASETS if d not in handle]
        if missing:
            raise ShardError(f"{path} lacks required dataset(s) {missing}")
        for d in REQUIRED_DATASETS:
            if d != "psf" and handle[d].shape[0] != n:
                raise ShardError(
                    f"{path}: dataset {d} has {handle[d].shape[0]} rows, n_images = {n}"
                )
        # Touch the last image: a truncated file fails here rather than mid-training.
        if n:
            CheckedRows(path, handle["images"])[n - 1]
    except ShardError:
        handle.close()
        raise
    except (OSError, KeyError, ValueError) as exc:
        handle.close()
        raise ShardError(f"{path} is corrupt: {exc}") from None
    shard = Shard(path, handle)
    problem = placement_problem(path, shard.attrs)
    if problem is not None:
        shard.close()
        raise ShardError(problem)
    return shard


def verify_shard(path: str | os.PathLike[str]) -> int:
    """Read every dataset of a shard whole (every chunk's checksum checked by HDF5) and
    return the number of images; a bad chunk raises :class:`ShardError` naming the
    dataset and the image or row."""
    with open_shard(path) as shard:
        datasets: list[h5py.Dataset] = []
        shard.file.visititems(
            lambda _, obj: datasets.append(obj) if isinstance(obj, h5py.Dataset) else None
        )
        for dataset in datasets:
            rows = CheckedRows(shard.path, dataset)
            if not dataset.shape:  # a scalar
                rows[()]
                continue
            for lo in range(0, len(rows), 256):
                rows[lo : lo + 256]
        return len(shard)
