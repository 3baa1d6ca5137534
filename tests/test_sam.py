"""The `sam` segmenter end to end in its own environment (`umad_common/scripts/sam_env.sh`): a randomly initialised
vit_b saved as a checkpoint file, loaded by the operator, run on a small frame -- the real code path.

Runs only when UMAD_SAM_PYTHON names that environment's python; the errors the main environment
gives at construction are tested in test_segmenter.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import textwrap
from pathlib import Path

import pytest

SAM_PYTHON = os.environ.get("UMAD_SAM_PYTHON", "")
REPO_ROOT = Path(__file__).resolve().parents[1]

END_TO_END = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import torch
    from segment_anything import sam_model_registry
    from umad_operators.segmenter import Segmenter
    from umad_common.dataflow.api.messages import Message
    from umad_common.dataflow import Frame

    torch.set_num_threads(1)
    torch.manual_seed(0)
    checkpoint = sys.argv[1]
    torch.save(sam_model_registry["vit_b"](checkpoint=None).state_dict(), checkpoint)
    op = Segmenter({"method": "sam", "options": {"checkpoint": checkpoint, "model": "vit_b", "points_per_side": 4,
                                                 "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0}})
    rng = np.random.default_rng(0)
    target = rng.random((48, 64, 3), dtype=np.float32)
    target[12:30, 20:44] = (0.9, 0.1, 0.1)
    frame = Frame("run", 0, 0, inputs={"frame": Message("run", 0, arrays={"target": target})})
    out = op.process(frame)["masks"]
    masks = out.arrays["masks"]
    print(json.dumps({"shape": list(masks.shape), "mask_pixels": masks.sum(axis=(1, 2)).tolist(), "dtype": str(masks.dtype), "meta": out.meta,
                      "torch": torch.__version__}))
    """
)


@pytest.mark.skipif(not SAM_PYTHON, reason="UMAD_SAM_PYTHON does not name the SAM environment's python")
def test_sam_end_to_end_with_random_vit_b(tmp_path):
    result = subprocess.run(
        [SAM_PYTHON, "-c", END_TO_END, str(tmp_path / "vit_b_random.pth")],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert result.returncode == 0, result.stderr[-4000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["torch"].startswith("2.14.1")
    k, h, w = report["shape"]
    assert (h, w) == (48, 64) and k >= 0
    assert report["dtype"] == "bool"
    assert report["meta"] == {"method": "sam", "count": k}
    assert report["mask_pixels"] == sorted(report["mask_pixels"], reverse=True)  # largest first
