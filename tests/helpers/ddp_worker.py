"""Run by ``torchrun`` in tests/training/test_trainer_ddp.py: ``smdm train``'s own entry point, instrumented.

    torchrun --nproc_per_node 2 tests/helpers/ddp_worker.py DUMP_DIR -- <smdm train arguments>

Each rank writes to DUMP_DIR: ``rank<r>.pt`` (its model's parameters and buffers after training)
and ``rank<r>_writes.json`` (every file the trainer module wrote). Nothing else is changed.
"""
import json
import os
import sys

import torch


def main() -> int:
    dump, argv = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
    import smdm_plugin.apps.train as cli
    import smdm_plugin.training.trainer as tr

    rank = int(os.environ.get("RANK", "0"))
    writes = []
    for module in (tr, cli):  # the trainer's checkpoints, the command's logs
        for name in ("atomic_open", "atomic_write_json", "atomic_write_text"):
            original = getattr(module, name)

            def recording(path, *a, _original=original, **k):
                writes.append(os.fspath(path))
                return _original(path, *a, **k)

            setattr(module, name, recording)
    train = tr.Trainer.train

    def train_and_dump(self, *a, **k):
        result = train(self, *a, **k)
        torch.save({n: v.detach().clone() for n, v in self.model.state_dict().items()},
                   os.path.join(dump, f"rank{rank}.pt"))
        return result

    tr.Trainer.train = train_and_dump
    try:
        return cli.main(argv)
    finally:
        with open(os.path.join(dump, f"rank{rank}_writes.json"), "w") as f:
            json.dump(writes, f)


if __name__ == "__main__":
    sys.exit(main())
