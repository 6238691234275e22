"""One-off: do RLBench's own readers read our training-data export as it is?

Exports 2 tasks x 2 demos with ``agnostos_mjx.data.export`` (RLBench's five cameras, 128 px),
keeping our own arrays (float depth, point clouds, segmentation, proprioception) aside, then
in a second Python (``--reader-python``: numpy 1.x, pillow, natsort, as PerAct's and RVT's
environments) loads the episodes with

* ``rlbench.utils.get_stored_demos`` of PerAct's RLBench fork (branch ``peract``, the one
  PerAct and RVT install), ``variation_number=-1`` on our ``all_variations`` folders;
* ``rlbench.utils.get_stored_demos`` of upstream RLBench (stepjam/RLBench), through a view of
  symlinks ``<task>/variation<v>/episodes/episode<i>`` (upstream has no ``all_variations``);
* RVT's loader, ``peract_colab.rlbench.utils.get_stored_demo``;

and compares what they return with our arrays.  PerAct's ``keypoint_discovery`` runs on
every loaded demo.  Sources come from local git clones (``--rlbench-git`` etc.); only the
``.py`` files of ``rlbench/`` are checked out (its .ttm scenes are not needed to read).

What is stubbed (nothing on the reading path of ``get_stored_demos``):

* ``pyrep`` (needs CoppeliaSim): ``pyrep.const.RenderMode`` (an enum, only a default argument
  of ``CameraConfig``) and ``pyrep.objects.VisionSensor`` whose only member,
  ``pointcloud_from_depth_and_camera_params``, is PyRep's own code: the static method and its
  three module helpers are taken from PyRep's ``pyrep/objects/vision_sensor.py`` at the given
  commit with ``ast`` and executed as they are (not retyped);
* ``rlbench/__init__.py`` is not executed (the package is registered with its ``__path__``):
  it imports the simulator (``Environment``, PyRep) and, upstream, registers gymnasium
  environments; ``rlbench.utils`` and what it imports run unchanged.

Usage (from the repository root, our environment)::

    python eval/reports/rlbench_reader_check/check.py --reader-python /tmp/rlbcheck-venv/bin/python

The report (markdown) goes to stdout; ``--keep DIR`` keeps the exported data.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

TASKS = ("open_drawer", "push_buttons")
PERACT_CAMERAS = ("front", "left_shoulder", "right_shoulder", "wrist")
SIZE = 128
MIRRORS = "/work/.mirror"
PYREP_HELPERS = ("_create_uniform_pixel_coords_image", "_transform", "_pixel_to_world_coords")


def git(repo: str, *args: str) -> str:
    return subprocess.run(["git", "-C", repo, *args], check=True, capture_output=True,
                          text=True).stdout


def checkout_py(repo: str, ref: str, folder: str, dest: Path) -> str:
    """The .py files under `folder` at `ref` -> dest; returns the full commit hash."""
    commit = git(repo, "rev-parse", ref).strip()
    for name in git(repo, "ls-tree", "-r", "--name-only", commit, folder).split():
        if name.endswith(".py"):
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            (dest / name).write_text(git(repo, "show", f"{commit}:{name}"))
    return commit


# ---- step 1 (our environment): export, keeping our arrays ------------------------------------
def export(data: Path, ref: Path) -> dict:
    from agnostos_mjx.data import export as ex

    write = ex.write_episode

    def keep(path, frames, description, variation):
        arrays = {"gripper_pose": [f["gripper_pose"] for f in frames],
                  "joint_positions": [f["joint_positions"] for f in frames]}
        for cam in PERACT_CAMERAS:
            for kind in ("rgb", "depth", "point_cloud", "mask"):
                arrays[f"{cam}_{kind}"] = [f[f"{cam}_{kind}"] for f in frames]
        name = f"{path.parents[2].name}_{path.name}"
        np.savez_compressed(ref / f"{name}.npz", **{k: np.stack(v) for k, v in arrays.items()})
        (ref / f"{name}.json").write_text(json.dumps({"descriptions": description,
                                                      "variation": int(variation)}))
        write(path, frames, description, variation)

    ex.write_episode = keep
    cfg = ex.ExportConfig(out=data, tasks=TASKS, demos=2, size=SIZE, batch=2)
    try:
        return ex.export(cfg)
    finally:
        ex.write_episode = write


# ---- step 2 (reader environment): RLBench's readers ------------------------------------------
def install_stubs(src: Path, pyrep_source: str) -> None:
    import enum
    import types

    pyrep = types.ModuleType("pyrep")
    pyrep.__path__ = []
    pyrep.__version__ = "4.1.0.2"
    const = types.ModuleType("pyrep.const")

    class RenderMode(enum.Enum):
        OPENGL = 1
        OPENGL3 = 2
        OPENGL3_WINDOWED = 3

    const.RenderMode = RenderMode
    tree = ast.parse(pyrep_source)
    nodes = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name in PYREP_HELPERS]
    sensor = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "VisionSensor")
    method = next(n for n in sensor.body if isinstance(n, ast.FunctionDef)
                  and n.name == "pointcloud_from_depth_and_camera_params")
    stub = ast.Module(body=[*nodes, ast.ClassDef(name="VisionSensor", bases=[], keywords=[],
                                                 body=[method], decorator_list=[])],
                      type_ignores=[])
    objects = types.ModuleType("pyrep.objects")
    exec(compile("import numpy as np\nfrom typing import List\n" + ast.unparse(stub),
                 "pyrep/objects/vision_sensor.py (PyRep's functions)", "exec"), objects.__dict__)
    rlbench = types.ModuleType("rlbench")
    rlbench.__path__ = [str(src / "rlbench")]
    sys.modules.update({"pyrep": pyrep, "pyrep.const": const, "pyrep.objects": objects,
                        "rlbench": rlbench})
    sys.path.insert(0, str(src))


def load_module(name: str, path: Path):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compare(demo, ref: dict, meta: dict, keypoint_discovery, masks: bool) -> dict:
    n = len(ref["gripper_pose"])
    from rlbench.backend.utils import rgb_handles_to_mask

    out = {"frames": len(demo), "keyframes": n, "rgb_equal": True, "mask_equal": True,
           "mask_ids": masks,
           "depth_err_m": 0.0, "pcd_err_m": 0.0, "pose_equal": True, "joints_equal": True}
    assert len(demo) == n, (len(demo), n)
    for i, obs in enumerate(demo):
        for cam in PERACT_CAMERAS:
            rgb = getattr(obs, f"{cam}_rgb")
            assert rgb.shape == (SIZE, SIZE, 3) and rgb.dtype == np.uint8, (rgb.shape, rgb.dtype)
            out["rgb_equal"] &= bool(np.array_equal(rgb, ref[f"{cam}_rgb"][i]))
            depth = getattr(obs, f"{cam}_depth")
            out["depth_err_m"] = max(out["depth_err_m"], float(np.abs(
                depth - ref[f"{cam}_depth"][i]).max()))
            pcd = getattr(obs, f"{cam}_point_cloud")
            assert pcd.shape == (SIZE, SIZE, 3), pcd.shape
            out["pcd_err_m"] = max(out["pcd_err_m"], float(np.abs(
                pcd - ref[f"{cam}_point_cloud"][i]).max()))
            mask = getattr(obs, f"{cam}_mask")
            if masks:  # RVT's loader reads no masks
                ids = ref[f"{cam}_mask"][i] + 1
                out["mask_ids"] &= bool(np.array_equal(mask, ids))
                # What the reader makes of the PNG RLBench's save_demo writes for these ids
                # (handle = R + 256 G + 65536 B, uint8): PerAct's fork multiplies it by 255
                # in place first, so its masks are not the handles for anyone's data.
                v = ids.astype(np.int64)
                png = np.stack([v & 255, (v >> 8) & 255, (v >> 16) & 255], -1).astype(np.uint8)
                out["mask_equal"] &= bool(np.array_equal(mask, rgb_handles_to_mask(png)))
        out["pose_equal"] &= bool(np.array_equal(obs.gripper_pose,
                                                 ref["gripper_pose"][i].astype(np.float64)))
        out["joints_equal"] &= bool(np.array_equal(obs.joint_positions,
                                                   ref["joint_positions"][i].astype(np.float64)))
    out["variation_ok"] = getattr(demo, "variation_number", None) == meta["variation"]
    descriptions = demo[0].misc.get("descriptions")
    out["descriptions_ok"] = None if descriptions is None else descriptions == meta["descriptions"]
    out["ignore_collisions"] = sorted({float(o.ignore_collisions) for o in demo})
    out["keypoints"] = [int(k) for k in keypoint_discovery(demo)]
    assert out["pcd_err_m"] < 0.01 and out["depth_err_m"] < 1e-3, out
    assert out["rgb_equal"] and out["mask_equal"] and out["pose_equal"], out
    assert out["joints_equal"], out
    return out


def read(args) -> None:
    install_stubs(Path(args.src), Path(args.pyrep_file).read_text())
    if args.extra_path:
        sys.path.append(args.extra_path)
    from rlbench.observation_config import ObservationConfig
    from rlbench.utils import get_stored_demos

    keypoint_discovery = load_module("peract_demo_loading_utils",
                                     Path(args.peract_file)).keypoint_discovery
    cfg = ObservationConfig()
    cfg.set_all(True)
    cfg.overhead_camera.set_all(False)
    for cam in PERACT_CAMERAS:
        camera = getattr(cfg, f"{cam}_camera")
        camera.image_size = (SIZE, SIZE)
        camera.depth_in_meters = True
        camera.mask = not args.no_masks
    data, ref = Path(args.data), Path(args.ref)
    results = []
    for task in TASKS:
        for i in range(2):
            arrays = dict(np.load(ref / f"{task}_episode{i}.npz"))
            meta = json.loads((ref / f"{task}_episode{i}.json").read_text())
            if args.flavour == "peract":
                demo = get_stored_demos(1, False, str(data), -1, task, cfg, False, i)[0]
            elif args.flavour == "upstream":
                view = Path(args.view)
                v = meta["variation"]
                folder = view / task / f"variation{v}" / "episodes"
                folder.mkdir(parents=True, exist_ok=True)
                link = folder / f"episode{i}"
                if not link.exists():
                    link.symlink_to(data / task / "all_variations" / "episodes" / f"episode{i}")
                from natsort import natsorted

                j = natsorted(os.listdir(folder)).index(f"episode{i}")
                demo = get_stored_demos(1, False, str(view), v, task, cfg, False, j)[0]
            else:  # RVT
                rvt = load_module("peract_colab_rlbench_utils", Path(args.rvt_file))
                demo = rvt.get_stored_demo(str(data / task / "all_variations" / "episodes"), i)
            results.append({"task": task, "episode": i, **compare(
                demo, arrays, meta, keypoint_discovery,
                masks=args.flavour != "rvt" and not args.no_masks)})
    print(json.dumps({"numpy": np.__version__, "python": sys.version.split()[0],
                      "results": results}))


# ---- driver ----------------------------------------------------------------------------------
def main() -> int:
    from agnostos_mjx.infra.settings import configure_jax

    configure_jax()  # as the commands do, before JAX starts
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("step", nargs="?", default="all", choices=("all", "read"))
    p.add_argument("--reader-python", default=sys.executable)
    p.add_argument("--rlbench-git", default=f"{MIRRORS}/MohitShridhar+RLBench/repo")
    p.add_argument("--rlbench-ref", default="peract")
    p.add_argument("--upstream-git", default=f"{MIRRORS}/stepjam+RLBench/repo")
    p.add_argument("--pyrep-git", default=f"{MIRRORS}/stepjam+PyRep/repo")
    p.add_argument("--peract-git", default=f"{MIRRORS}/peract+peract/repo")
    p.add_argument("--colab-git", default=f"{MIRRORS}/peract+peract_colab/repo")
    p.add_argument("--keep", help="keep the exported data and sources here")
    p.add_argument("--no-masks", action="store_true",
                   help="readers skip masks (RLBench's mask decoding overflows under numpy 2)")
    p.add_argument("--extra-path", help="appended to the reader's sys.path (e.g. natsort)")
    # read step (internal)
    for name in ("src", "pyrep-file", "peract-file", "rvt-file", "data", "ref", "view",
                 "flavour"):
        p.add_argument(f"--{name}")
    args = p.parse_args()
    if args.step == "read":
        read(args)
        return 0
    work = Path(args.keep or tempfile.mkdtemp(prefix="rlbench_reader_check_"))
    data, ref, src = work / "data", work / "ref", work / "src"
    for d in (data, ref, src):
        d.mkdir(parents=True, exist_ok=True)
    commits = {
        "RLBench (PerAct fork)": (args.rlbench_git,
                                  checkout_py(args.rlbench_git, args.rlbench_ref, "rlbench",
                                              src / "peract")),
        "RLBench (upstream)": (args.upstream_git,
                               checkout_py(args.upstream_git, "HEAD", "rlbench",
                                           src / "upstream")),
        "PyRep": (args.pyrep_git, checkout_py(args.pyrep_git, "HEAD", "pyrep/objects", src)),
        "PerAct": (args.peract_git, checkout_py(args.peract_git, "HEAD", "helpers", src)),
        "peract_colab (RVT)": (args.colab_git, checkout_py(args.colab_git, "HEAD", "rlbench",
                                                           src / "colab")),
    }
    with contextlib.redirect_stdout(sys.stderr):  # the export's estimate line
        manifest = export(data, ref)
    print("# RLBench's own readers read our export\n")
    print("Sources (local clones; commit):\n")
    for name, (repo, commit) in commits.items():
        print(f"- {name}: `{commit}` ({Path(repo).parent.name.replace('+', '/')})")
    print(f"\nExport: {', '.join(TASKS)} x 2 demos, cameras {manifest['config']['cameras']}, "
          f"{SIZE} px, format {manifest['config']['format']}.\n")
    flavours = {"peract": src / "peract", "upstream": src / "upstream", "rvt": src / "peract"}
    common = ["--pyrep-file", str(src / "pyrep/objects/vision_sensor.py"),
              "--peract-file", str(src / "helpers/demo_loading_utils.py"),
              "--rvt-file", str(src / "colab/rlbench/utils.py"),
              "--data", str(data), "--ref", str(ref), "--view", str(work / "view"),
              *(["--no-masks"] if args.no_masks else []),
              *(["--extra-path", args.extra_path] if args.extra_path else [])]
    readers = {"peract": "PerAct fork `rlbench.utils.get_stored_demos(variation_number=-1)`",
               "upstream": "upstream `rlbench.utils.get_stored_demos(variation_number=v)`",
               "rvt": "RVT's `peract_colab.rlbench.utils.get_stored_demo`"}
    failures = 0
    for flavour, folder in flavours.items():
        cmd = [args.reader_python, __file__, "read", "--flavour", flavour, "--src", str(folder),
               *common]
        run = subprocess.run(cmd, capture_output=True, text=True)
        print(f"## {readers[flavour]}\n")
        if run.returncode:
            failures += 1
            print("FAILED:\n\n```\n" + run.stderr[-3000:] + "\n```\n")
            continue
        report = json.loads(run.stdout.strip().splitlines()[-1])
        print(f"Reader: Python {report['python']}, numpy {report['numpy']}.\n")
        print("| episode | frames / keyframes | rgb equal | depth max err (m) | point cloud max "
              "err (m) | masks = our ids + 1 (as the reader decodes RLBench's mask PNGs) "
              "| pose, joints equal | variation, descriptions "
              "| PerAct keypoints |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in report["results"]:
            masks = ("not read" if flavour == "rvt" or args.no_masks
                     else f"{r['mask_ids']} ({r['mask_equal']})")
            print(f"| {r['task']} {r['episode']} | {r['frames']} / {r['keyframes']} | "
                  f"{r['rgb_equal']} | {r['depth_err_m']:.1e} | {r['pcd_err_m']:.1e} | "
                  f"{masks} | {r['pose_equal'] and r['joints_equal']} | "
                  f"{r['variation_ok']}, {r['descriptions_ok']} | {r['keypoints']} |")
        print()
    print(f"Data: {work}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
