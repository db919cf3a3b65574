"""osvp trains from `storage` alone: with datagen, Ray, Embree, trimesh and HiGHS made unimportable,
a fresh interpreter loads the dataset with its minimum covers, trains one epoch on them, scores a
cloud and decodes the probabilities."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

BLOCKED = ("datagen", "ray", "embreex", "trimesh", "highspy", "jobs")

SCRIPT = """
import sys
BLOCKED = {blocked!r}

class Blocker:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"blocked in this test: {{name}}")
        return None

sys.meta_path.insert(0, Blocker())
from pathlib import Path
from osvp.train import TrainOptions, train
from osvp.planning import load_scorer
import numpy as np
out = Path({out!r})
train(TrainOptions(data={url!r}, out=out, epochs=1, batch_size=32, target="mincover"))
scorer = load_scorer(out / "best.pt")
state = np.zeros(32, dtype=np.float32); state[0] = 1
p = scorer.view_probabilities(np.random.default_rng(0).normal(0, 0.05, (500, 3)).astype(np.float32), state)
assert p.shape == (32,) and ((p >= 0) & (p <= 1)).all()
for decoding in (None, "size", "threshold=0.3"):
    assert not scorer.select_views(p, state, decoding)[0]
leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
assert not leaked, leaked
print("trained without", ", ".join(BLOCKED))
"""


def test_training_and_scoring_need_none_of_the_generator(dataset_url: str, tmp_path: Path) -> None:
    code = SCRIPT.format(blocked=BLOCKED, out=str(tmp_path / "run"), url=dataset_url)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}  # a tiny network: one thread is fastest on a busy machine
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    assert "trained without" in done.stdout
