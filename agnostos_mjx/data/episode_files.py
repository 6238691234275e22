"""One episode folder in RLBench's format: written atomically with its SHA256SUMS,
verified against them, and read back without rlbench - every pickle through the
restricted unpickler of data/rlbench_demo.py, so an episode received from elsewhere cannot
run code when it is read."""

from __future__ import annotations

import hashlib
import json
import pickle
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from agnostos_mjx.data.rlbench_demo import (
    DESCRIPTIONS_PICKLE,
    LOW_DIM_PICKLE,
    NUMBER_PICKLE,
    Demo,
    dumps,
    read_pickle,
)
from agnostos_mjx.data.rlbench_format import (
    KEYFRAMES,
    LOW_DIM_FIELDS,
    SUMS,
    decode_depth,
    encode_depth,
    int_to_rgb,
    rgb_to_int,
    rlbench_observation,
)


def _png(path: Path, img: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(img)).save(path, compress_level=1)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_episode(path: Path, frames: list[dict], description: list[str], variation: int,
                  keyframes: Sequence[int] | None = None) -> None:
    """One demo's frames (RLBenchObservation.world dicts) -> an episode folder, atomically;
    `keyframes` (indices of the keyframes among dense frames) go to keyframes.json."""
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    cameras = [k[: -len("_camera_near")] for k in frames[0]["misc"] if k.endswith("_camera_near")]
    for k, f in enumerate(frames):
        for cam in cameras:
            near, far = f["misc"][f"{cam}_camera_near"], f["misc"][f"{cam}_camera_far"]
            images = {"rgb": f.get(f"{cam}_rgb")}
            if f.get(f"{cam}_depth") is not None:
                images["depth"] = encode_depth(f[f"{cam}_depth"], near, far)
            if f.get(f"{cam}_mask") is not None:
                images["mask"] = int_to_rgb(f[f"{cam}_mask"] + 1)
            for kind, img in images.items():
                if img is not None:
                    (tmp / f"{cam}_{kind}").mkdir(exist_ok=True)
                    _png(tmp / f"{cam}_{kind}" / f"{k}.png", img)
    demo = Demo([rlbench_observation(f, cameras) for f in frames], None, int(variation))
    (tmp / LOW_DIM_PICKLE).write_bytes(dumps(demo))
    (tmp / DESCRIPTIONS_PICKLE).write_bytes(pickle.dumps(list(description)))
    (tmp / NUMBER_PICKLE).write_bytes(pickle.dumps(int(variation)))
    if keyframes is not None:
        (tmp / KEYFRAMES).write_text(json.dumps([int(k) for k in keyframes]) + "\n")
    files = sorted(p for p in tmp.rglob("*") if p.is_file())
    sums = "".join(f"{_sha256(p)}  {p.relative_to(tmp)}\n" for p in files)
    (tmp / SUMS).write_text(sums)
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)


def verify_episode(path: Path) -> None:
    """Raise ValueError naming the first file whose checksum does not match, or that
    SHA256SUMS does not list."""
    listed = set()
    for line in (path / SUMS).read_text().splitlines():
        digest, name = line.split("  ", 1)
        listed.add(name)
        if not (path / name).is_file() or _sha256(path / name) != digest:
            raise ValueError(f"checksum mismatch: {path / name}")
    for p in sorted(path.rglob("*")):
        if p.is_file() and p.name != SUMS and str(p.relative_to(path)) not in listed:
            raise ValueError(f"not in {SUMS}: {p}")


def read_episode(path: Path, verify: bool = True) -> dict:
    """An exported episode -> {"demo": the unpickled ``low_dim_obs.pkl`` (stand-in
    ``Demo``), "low_dim": {field or misc key: per-frame stack}, "<cam>_rgb"/"_depth"
    (metres)/"_mask" (geom id, -1 none): (T, H, W[, 3]) arrays, "descriptions",
    "variation", "keyframes": indices of the keyframes (every frame unless dense)}.
    Needs no rlbench.  The pickles are read with a restricted unpickler (only the globals
    each file needs: rlbench_demo.read_pickle); a pickle naming anything else raises
    pickle.UnpicklingError naming the file, before any of it runs."""
    from PIL import Image

    path = Path(path)
    if verify:
        verify_episode(path)
    demo = read_pickle(path / LOW_DIM_PICKLE)
    low = {name: np.stack([np.asarray(getattr(o, name)) for o in demo])
           for name in LOW_DIM_FIELDS}
    low.update({key: np.stack([np.asarray(o.misc[key]) for o in demo]) for key in demo[0].misc})
    out: dict = {"demo": demo, "low_dim": low,
                 "descriptions": read_pickle(path / DESCRIPTIONS_PICKLE),
                 "variation": read_pickle(path / NUMBER_PICKLE)}
    n = len(demo)
    keys = path / KEYFRAMES
    out["keyframes"] = json.loads(keys.read_text()) if keys.exists() else list(range(n))
    for folder in sorted(p for p in path.iterdir() if p.is_dir()):
        cam, kind = folder.name.rsplit("_", 1)
        imgs = np.stack([np.asarray(Image.open(folder / f"{k}.png")) for k in range(n)])
        if kind == "depth":
            imgs = np.stack([decode_depth(im, float(low[f"{cam}_camera_near"][k]),
                                          float(low[f"{cam}_camera_far"][k]))
                             for k, im in enumerate(imgs)])
        elif kind == "mask":
            imgs = (rgb_to_int(imgs) - 1).astype(np.int32)
        out[folder.name] = imgs
    return out
