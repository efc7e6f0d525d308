"""DistributedDataParallel on the CPU: 2 processes under torchrun (gloo) end a step with identical weights."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

HERE = Path(__file__).resolve().parent  # the worker imports this folder's test_train

WORKER = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    import torch
    import torch.distributed as dist

    sys.path.insert(0, sys.argv[2])
    from test_train import TINY, tiny_data, tiny_run
    from dmlo.train import Trainer
    from dmlo.train.distributed import DistributedBatchNorm2d, init_distributed

    out = Path(sys.argv[1])
    context = init_distributed(torch.device("cpu"))
    assert context.world_size == 2
    trainer = Trainer(TINY, tiny_run(out / "run", batch_size=1, max_steps=2), tiny_data(), context=context, progress=False)
    assert any(isinstance(m, DistributedBatchNorm2d) for m in trainer.model.modules())
    initial = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    trainer.run()
    torch.save({"initial": initial, "final": trainer.model.state_dict()}, out / f"rank{context.rank}.pt")
    dist.destroy_process_group()
    """
)


@pytest.mark.slow
def test_two_cpu_processes_hold_identical_weights_after_steps(tmp_path) -> None:
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    command = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
        str(script), str(tmp_path), str(HERE),
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in (0, 1)]
    changed = False
    for name, value in ranks[0]["final"].items():
        # Weights and BatchNorm statistics agree exactly: gradients are averaged, statistics synchronised.
        torch.testing.assert_close(value, ranks[1]["final"][name], rtol=0, atol=0, msg=name)
        changed |= not torch.equal(value, ranks[0]["initial"][name])
    assert changed
    assert (tmp_path / "run" / "last.pt").is_file()
