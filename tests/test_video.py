"""Episode videos: --video writes one MP4 per selected episode with one frame per key action."""

from __future__ import annotations

import json

import numpy as np
import pytest

av = pytest.importorskip("av")


def _probe(path) -> tuple[int, float, tuple[int, int]]:
    """(decoded frames, duration in seconds, (height, width)) read back with PyAV."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f for f in container.decode(stream)]
        duration = float(stream.duration * stream.time_base) if stream.duration else \
            float(container.duration / av.time_base)
        return len(frames), duration, (frames[0].height, frames[0].width)


def test_eval_writes_selected_episode_videos(tmp_path) -> None:
    from agnostos_mjx.evaluation.config import EvalConfig
    from agnostos_mjx.evaluation.run import evaluate
    from agnostos_mjx.evaluation.video import VideoSpec

    cfg = EvalConfig.of(policy="oracle", tasks="lamp_on,close_microwave", seeds=[0], episodes=4,
                        batch=4, backend="native", out=str(tmp_path), quiet=True,
                        video="first:3", video_cameras="front,wrist")
    results = evaluate(cfg)
    videos = sorted((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 6  # 2 tasks x episodes 0..2; episode 3 not filmed
    fps = VideoSpec().fps
    for rec in results["episodes"]:
        stem = f"{rec['task']}_s0_e{rec['episode']:03d}_{rec['outcome']}"
        path = tmp_path / "videos" / f"{stem}.mp4"
        assert path.exists() == (rec["episode"] < 3), stem
        if rec["episode"] < 3:
            frames, duration, shape = _probe(path)
            assert frames == rec["key_actions"] + 1  # after reset, then each key action
            assert duration == pytest.approx(frames / fps, abs=0.01)
            assert shape == (256, 2 * 256)  # front | wrist
            assert json.loads(path.with_suffix(".json").read_text())["episode"] == rec["episode"]


def test_video_spec_parsing_and_llm_text(tmp_path) -> None:
    from agnostos_mjx.evaluation.video import VideoSpec, _llm_text, write_mp4

    assert VideoSpec.parse("failures:5").failures_only and VideoSpec.parse("failures").first is None
    assert VideoSpec.parse("first:2", "front").cameras == ("front",)
    for bad in ("first", "all", "first:x"):
        with pytest.raises(ValueError):
            VideoSpec.parse(bad)
    info = {"plans": [{"prompt": "demo>", "response": "[[1, 2, 3, 4, 5, 6, 1]]"}]}
    assert "PROMPT:\ndemo>" in _llm_text(info) and _llm_text({"plans": []}) is None
    frames = np.random.default_rng(0).integers(0, 255, (5, 33, 47, 3), np.uint8)
    write_mp4(tmp_path / "odd.mp4", frames, fps=5.0)  # odd sizes are padded
    assert _probe(tmp_path / "odd.mp4")[:2] == (5, pytest.approx(1.0, abs=0.01))


@pytest.fixture(scope="module")
def memory_file(bank_dir, tmp_path_factory):
    from agnostos_mjx.data import DemoBank
    from agnostos_mjx.xicm.memory import DemoMemory

    path = tmp_path_factory.mktemp("memory") / "memory.npz"
    DemoMemory.from_bank(DemoBank(bank_dir)).save(path)
    return path


def test_xicm_with_segmented_objects_and_prompt_next_to_video(memory_file, tmp_path) -> None:
    """X-ICM's object text from segmented point clouds (--policy-arg objects=segmented),
    and the prompt and answer stored next to the episode's video."""
    import re

    from agnostos_mjx import eval as ev
    from agnostos_mjx.llm.testing import ScriptedLLMServer

    def press(msgs) -> str:
        query = msgs[-1]["content"].rsplit("]], ", 1)[-1]
        x, y, z = map(int, re.search(r"'button': \[(\d+), (\d+), (\d+)\]", query).groups())
        return f"[[{x}, {y}, {z + 8}, 0, 36, 0, 0], [{x}, {y}, {z + 1}, 0, 36, 0, 0]]"

    out = tmp_path / "run"
    with ScriptedLLMServer(press) as server:
        assert ev.main(["--llm-url", server.url, "--llm-model", "scripted", "--tasks",
                        "lamp_on", "--seeds", "0", "--episodes", "2", "--batch", "2",
                        "--backend", "native", "--quiet", "--selection", "random",
                        "--num-demos", "3", "--memory", str(memory_file), "--out", str(out),
                        "--policy-arg", "objects=segmented", "--video", "first:1"]) == 0
    records = [json.loads(line) for line in (out / "episodes.jsonl").open()]
    assert all(r["success"] for r in records)
    (text,) = (out / "videos").glob("lamp_on_s0_e000_*.llm.txt")
    assert "'button': [" in text.read_text() and "ANSWER:\n[[" in text.read_text()
    assert len(list((out / "videos").glob("*.mp4"))) == 1
