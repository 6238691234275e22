"""Write (and with --run, execute) notebooks/dynamics_selection.ipynb."""

from __future__ import annotations

import sys
from pathlib import Path

import nbformat as nbf

cells = [
    nbf.v4.new_markdown_cell("""# Dynamics features and demonstration selection

X-ICM picks, for an unseen task, the K = 18 seen demonstrations whose *dynamics* look most like
it. The dynamics model (InstructPix2Pix-style latent diffusion, `agnostos_mjx/dynamics`)
predicts a demo's last frame from its first frame and instruction; its features are the pooled
text feature (`lang`), the first-frame latent (`vis.in`) and the predicted last-frame latent
(`vis.out`). This notebook uses only what ships with the package: the float16 export in
`agnostos_mjx/assets/dynamics` and the seen memory (3,600 demos with their features)."""),
    nbf.v4.new_code_cell("""import json
import os
from collections import Counter
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.xicm.dynamics_selector import (
    QUERY_SAMPLE_STEPS,
    default_checkpoint_path,
    load_pipeline,
)
from agnostos_mjx.xicm.memory import DemoMemory, default_memory_path

configure_jax()  # XLA's flags and JAX's compile cache, as the commands set them

# AGNOSTOS_NOTEBOOK_SMALL=1 (the tests): 3 unseen tasks, the policies' 10 DDIM steps.
SMALL = os.environ.get('AGNOSTOS_NOTEBOOK_SMALL') == '1'
memory = DemoMemory.load(default_memory_path())
pipeline = load_pipeline(sample_steps=QUERY_SAMPLE_STEPS if SMALL else None)
export = json.loads((default_checkpoint_path() / 'export.json').read_text())
print(len(memory), 'seen demos of', len(set(memory.task.tolist())), 'tasks; features',
      {k: v.shape for k, v in memory.features.items()})
print('UNet channels', export['model']['unet']['channels'], '| DDIM steps',
      pipeline.diffusion.sample_steps, '| guidance', export['diffusion']['image_guidance'],
      export['diffusion']['text_guidance'])"""),
    nbf.v4.new_markdown_cell("""## Predicted last frames of held-out seen demos

Columns: first frame | predicted last frame | true last frame, for seen demos held out from
training. The grid was decoded at the end of training (the export ships the encoder only, which
is all that feature extraction needs). On the 360 held-out demos the predicted last-frame latent
is 56.4% closer to the true one than the first-frame latent is."""),
    nbf.v4.new_code_cell("""report = Path('../eval/reports/dynamics_default_h200')
print(json.loads((report / 'eval.json').read_text())['prediction'])
plt.figure(figsize=(6, 10))
plt.imshow(plt.imread(report / 'dyn_samples.png'))
plt.axis('off');"""),
    nbf.v4.new_markdown_cell("""## Unseen tasks: first frame, predicted change, chosen demonstrations

For each of the 23 unseen tasks, one scene (variation 0, evaluation seed 0) is reset, its front
frame rendered and its instruction taken, exactly as the policies query the model. The middle
column shows the first-frame latent and the right column the predicted last-frame latent (three
of the four latent channels as RGB): where they differ is where the model expects the scene to
change. Seconds per query on a CPU core, much less on a GPU. (With
`AGNOSTOS_NOTEBOOK_SMALL=1`, as `tests/test_notebooks.py` runs it: three of the tasks.)"""),
    nbf.v4.new_code_cell("""from agnostos_mjx.dynamics.features import extract, similarity
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.evaluation.protocol import episode_keys
from agnostos_mjx.tasks import parse_tasks

unseen_tasks = parse_tasks('open_grill,close_laptop_lid,turn_oven_on' if SMALL else 'unseen')
unseen = [t.name for t in unseen_tasks]
frames, instructions = [], []
for task in unseen_tasks:
    runner = Episodes(task, 'native')
    env = runner.reset(episode_keys(np.array([0]), np.array([0])), np.array([0]))
    frames.append(runner.render(env, 'front', 128, 128)[0])
    instructions.append(task.descriptions(0)[0])
frames = np.stack(frames)
features = extract(pipeline, frames, instructions)
latent_in = features['vis.in'].reshape(-1, 16, 16, 4)
latent_out = features['vis.out'].reshape(-1, 16, 16, 4)"""),
    nbf.v4.new_code_cell("""def as_rgb(z):
    z = z[..., :3]
    return (z - z.min()) / (z.max() - z.min() + 1e-8)

rows = min(6, len(unseen))
fig, axes = plt.subplots(rows, 3, figsize=(7, 2.3 * rows), squeeze=False)
for r, i in enumerate(np.linspace(0, len(unseen) - 1, rows).astype(int)):
    axes[r, 0].imshow(frames[i])
    axes[r, 0].set_title(instructions[i][:32], fontsize=8)
    axes[r, 1].imshow(as_rgb(latent_in[i]))
    axes[r, 1].set_title('vis.in', fontsize=8)
    axes[r, 2].imshow(as_rgb(latent_out[i]))
    axes[r, 2].set_title('vis.out (predicted)', fontsize=8)
    for a in axes[r]:
        a.axis('off')
plt.tight_layout()"""),
    nbf.v4.new_markdown_cell("""### Where each unseen task's top-18 come from (`lang+vis.out`, cosine)"""),
    nbf.v4.new_code_cell("""sims = similarity(features, memory.features, 'lang+vis.out', 'cosine')
top = np.argsort(-sims, axis=1, kind='stable')[:, :18]
seen = sorted(set(memory.task.tolist()))
counts = np.zeros((len(unseen), len(seen)), int)
for q, idx in enumerate(top):
    for task, n in Counter(memory.task[idx].tolist()).items():
        counts[q, seen.index(task)] = n
    ranked = ', '.join(f'{t} x{n}' for t, n in Counter(memory.task[idx].tolist()).most_common())
    print(f'{unseen[q]:34s} {ranked}')"""),
    nbf.v4.new_code_cell("""fig, ax = plt.subplots(figsize=(10, 8))
ax.imshow(counts, cmap='viridis')
ax.set_xticks(range(len(seen)), seen, rotation=90, fontsize=7)
ax.set_yticks(range(len(unseen)), unseen, fontsize=7)
for q in range(len(unseen)):
    for s in range(len(seen)):
        if counts[q, s]:
            ax.text(s, q, counts[q, s], ha='center', va='center', fontsize=6, color='w')
ax.set_title('seen-task origin of the 18 selected demonstrations per unseen task')
plt.tight_layout()"""),
]

nb = nbf.v4.new_notebook(cells=cells, metadata={"kernelspec": {"name": "python3",
                                                              "display_name": "Python 3"}})
out = Path(__file__).resolve().parents[1] / "notebooks" / "dynamics_selection.ipynb"
if "--run" in sys.argv:
    from nbclient import NotebookClient

    NotebookClient(nb, timeout=1200, resources={"metadata": {"path": str(out.parent)}}).execute()
nbf.write(nb, out)
print("wrote", out)
