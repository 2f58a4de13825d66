"""On-disk cache of registration pairs, so that training never waits for rendering.

Layout of a cache directory (written by ``cegc-make-pairs``, see ``docs/data.md``)::

    cache.json                          settings the shards were made with (split, sensors, ...)
    shard_0000000_0000008.npz           rooms 0..7 of the split (room index, not seed)
    shard_0000008_0000016.npz           ...

A shard is an uncompressed ``.npz`` holding the fragments of a few rooms and the pairs made of
them (pairs of one room share fragments, so a fragment is stored once):

=================  ==================  ===================================================
member             dtype, shape        content
=================  ==================  ===================================================
``meta``           str (JSON)          format version, split, room seeds, counts
``frag_<k>``       int16 (N_k, 3)      fragment k, quantised: p = q * step + origin
``frag_origin``    float64 (F, 3)      per-fragment origin (metres)
``frag_step``      float64 (F,)        per-fragment step (metres; <= 0.1 mm for a 6 m cloud)
``pair_frags``     int32 (P, 2)        source and target fragment of each pair
``pair_T``         float64 (P, 4, 4)   T_target_source
``pair_crop``      float64 (P, 2, 4)   copy-protocol crops (direction xyz, keep); 0 otherwise
``pair_info``      str (JSON list)     one info dict per pair
=================  ==================  ===================================================

Points are stored as int16 with a per-fragment origin and step (6 bytes a point; the step is
the cloud's half extent / 32767, so a 6 m wide cloud is stored to 0.05 mm and a 60 m LiDAR
cloud to 1 mm), and returned as float32 metres. Shards are written to ``<name>.partial`` and
renamed, so a shard that exists is complete; generation resumes by skipping existing shards.

:class:`PairCache` reads a cache directory with cheap random access: it indexes the small pair
members of every shard once, and reads only the two fragments a pair needs (a zip member each).
"""

from __future__ import annotations

import json
import os
import re
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cegc_ros.data.codec import dequantise, quantise  # noqa: F401  (the shards' codec)
from cegc_ros.data.views import PairRecord, RoomPairs, materialise

if TYPE_CHECKING:
    from cegc_ros.data.protocols import Pair

FORMAT_VERSION = 1
MANIFEST = "cache.json"
_SHARD_RE = re.compile(r"^shard_(\d{7})_(\d{7})\.npz$")


class PairCacheError(Exception):
    """A cache directory or shard that cannot be read or written; the message names it."""


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def shard_name(first_room: int, end_room: int) -> str:
    """File name of the shard holding room indices [first_room, end_room) of a split."""
    return f"shard_{first_room:07d}_{end_room:07d}.npz"


def write_shard(path: str | Path, rooms: list[RoomPairs], meta: dict[str, Any]) -> int:
    """Write the rooms' fragments and pairs into shard ``path`` atomically; returns #pairs."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    origins, steps, frag_room = [], [], []
    pair_frags, pair_T, pair_crop, infos = [], [], [], []
    offset = 0
    for rp in rooms:
        for j, (q, origin, step) in enumerate(rp.codes):
            arrays[f"frag_{offset + j}"] = q
            origins.append(origin)
            steps.append(step)
            frag_room.append(rp.seed)
        for rec in rp.pairs:
            pair_frags.append((offset + rec.source, offset + rec.target))
            pair_T.append(rec.T_target_source)
            pair_crop.append(rec.crop)
            infos.append(rec.info)
        offset += len(rp.clouds)
    meta = dict(meta, format=FORMAT_VERSION, rooms=[rp.seed for rp in rooms], fragments=offset,
                pairs=len(infos))
    arrays.update(
        meta=np.array(json.dumps(meta)),
        frag_origin=np.array(origins, np.float64).reshape(-1, 3),
        frag_step=np.array(steps, np.float64),
        frag_room=np.array(frag_room, np.int64),
        pair_frags=np.array(pair_frags, np.int32).reshape(-1, 2),
        pair_T=np.array(pair_T, np.float64).reshape(-1, 4, 4),
        pair_crop=np.array(pair_crop, np.float64).reshape(-1, 2, 4),
        pair_info=np.array(json.dumps(infos)))
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    os.replace(tmp, path)
    return len(infos)


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def read_manifest(root: str | Path) -> dict[str, Any]:
    """The cache's settings ({} when the directory has no cache.json yet)."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise PairCacheError(f"{path}: unreadable manifest: {err}") from err


def list_shards(root: str | Path) -> list[Path]:
    """Complete shards of a cache directory, in room order."""
    root = Path(root)
    return sorted(p for p in root.iterdir() if _SHARD_RE.match(p.name))


class PairCache:
    """Random access to the pairs of a cache directory.

    ``PairCache(path, kinds=None, sensors=None, split=None)``: ``kinds`` / ``sensors`` keep only
    pairs whose info has that kind ("views", "copy") / sensor ("kinect", "lidar"); ``split``
    raises PairCacheError unless the cache was made for that split.

    ``len(cache)``; ``cache[i]`` -> :class:`cegc_ros.data.protocols.Pair` with ``source``
    (N, 3) float32 metres, ``target`` (M, 3) float32 metres (each in its own sensor frame; any
    prefix is a uniform subsample), ``T_target_source`` (4, 4) float64, ``info`` dict (kind,
    sensor, overlap, overlap_target, overlap_radius, room_seed, room_kind, split,
    rotation_deg, translation_m, ...). ``cache.infos`` lists the info dicts without loading
    clouds; ``cache.refresh()`` indexes shards written since (a cache can be read while it
    grows). Picklable (DataLoader workers): open shard handles are per process.
    """

    def __init__(self, path: str | Path, kinds: tuple[str, ...] | None = None,
                 sensors: tuple[str, ...] | None = None, split: str | None = None,
                 max_open: int = 32) -> None:
        self.root = Path(path)
        if not self.root.is_dir():
            raise PairCacheError(f"pair cache {self.root} is not a directory")
        self.kinds = tuple(kinds) if kinds is not None else None
        self.sensors = tuple(sensors) if sensors is not None else None
        self.manifest = read_manifest(self.root)
        if split is not None and self.manifest.get("split") not in (None, split):
            raise PairCacheError(f"pair cache {self.root} holds split "
                                 f"{self.manifest.get('split')!r}, expected {split!r}")
        self.split = split or self.manifest.get("split")
        self.max_open = max_open
        self._shards: list[Path] = []
        self._pair_shard: list[int] = []
        self._pair_local: list[int] = []
        self.infos: list[dict[str, Any]] = []
        self._tables: list[dict[str, np.ndarray]] = []
        self._handles: OrderedDict[int, Any] = OrderedDict()
        self.refresh()

    # ---- index ----
    def refresh(self) -> int:
        """Index shards not indexed yet; returns how many pairs were added."""
        known = {p.name for p in self._shards}
        added = 0
        for path in list_shards(self.root):
            if path.name in known:
                continue
            try:
                with np.load(path) as z:
                    meta = json.loads(str(z["meta"]))
                    table = {k: z[k] for k in ("pair_frags", "pair_T", "pair_crop",
                                               "frag_origin", "frag_step")}
                    infos = json.loads(str(z["pair_info"]))
            except (OSError, ValueError, KeyError, json.JSONDecodeError) as err:
                raise PairCacheError(f"{path}: unreadable shard: {err}") from err
            if meta.get("format") != FORMAT_VERSION:
                raise PairCacheError(f"{path}: shard format {meta.get('format')}, this reader "
                                     f"reads {FORMAT_VERSION}")
            if self.split is not None and meta.get("split") != self.split:
                raise PairCacheError(f"{path}: shard of split {meta.get('split')!r} in a "
                                     f"{self.split!r} cache")
            sid = len(self._shards)
            self._shards.append(path)
            self._tables.append(table)
            for k, info in enumerate(infos):
                if self.kinds is not None and info.get("kind") not in self.kinds:
                    continue
                if self.sensors is not None and info.get("sensor") not in self.sensors:
                    continue
                self._pair_shard.append(sid)
                self._pair_local.append(k)
                self.infos.append(info)
                added += 1
        return added

    def __len__(self) -> int:
        return len(self.infos)

    @property
    def overlaps(self) -> np.ndarray:
        """(len,) float64 overlap of every pair (from the index, no cloud loaded)."""
        return np.array([info["overlap"] for info in self.infos], np.float64)

    @property
    def room_seeds(self) -> set[int]:
        return {int(info["room_seed"]) for info in self.infos}

    # ---- access ----
    def _handle(self, sid: int) -> Any:
        h = self._handles.get(sid)
        if h is None:
            try:
                h = np.load(self._shards[sid])
            except (OSError, ValueError) as err:
                raise PairCacheError(f"{self._shards[sid]}: cannot open: {err}") from err
            self._handles[sid] = h
            if len(self._handles) > self.max_open:
                _, old = self._handles.popitem(last=False)
                old.close()
        else:
            self._handles.move_to_end(sid)
        return h

    def _cloud(self, sid: int, frag: int) -> np.ndarray:
        t = self._tables[sid]
        try:
            q = self._handle(sid)[f"frag_{frag}"]
        except (OSError, ValueError, KeyError) as err:
            raise PairCacheError(f"{self._shards[sid]}: fragment {frag} unreadable: {err}"
                                 ) from err
        return dequantise(q, t["frag_origin"][frag], float(t["frag_step"][frag]))

    def __getitem__(self, i: int) -> Pair:
        n = len(self.infos)
        if not -n <= i < n:
            raise IndexError(f"pair {i} outside 0..{n - 1}")
        i %= n
        sid, k = self._pair_shard[i], self._pair_local[i]
        t = self._tables[sid]
        s, g = (int(x) for x in t["pair_frags"][k])
        info = self.infos[i]
        rec = PairRecord(info.get("kind", "views"), s, g, t["pair_T"][k], t["pair_crop"][k], info)
        src = self._cloud(sid, s)
        tgt = src if g == s else self._cloud(sid, g)
        return materialise(rec, src, tgt)

    def close(self) -> None:
        for h in self._handles.values():
            h.close()
        self._handles.clear()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_handles"] = OrderedDict()
        return state
