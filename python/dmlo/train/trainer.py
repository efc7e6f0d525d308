"""The training loop: SGD with a step schedule (§IV-B), checkpoints, resume, DDP, validation."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

from dmlo.model import Matcher, MatcherConfig, matching_loss
from dmlo.model.confidence_loss import confidence_loss
from dmlo.model.pose_loss import pose_loss
from dmlo.train import checkpoint
from dmlo.train.config import TrainConfig
from dmlo.train.dataset import collate
from dmlo.train.distributed import DistributedContext, convert_batchnorm, resolve_device
from dmlo.train.metrics import FlowErrorSums, PoseErrorSums

LAST = "last.pt"
BEST = "best.pt"


def epoch_batches(size: int, batch_size: int, seed: int, epoch: int, context: DistributedContext) -> list[list[int]]:
    """This process's batches of one epoch: one seeded permutation shared by all processes, dealt out so
    every process runs the same number of full batches."""
    order = np.random.default_rng([seed, epoch, 0x5EED]).permutation(size)
    per_process = size // context.world_size
    mine = order[context.rank * per_process : (context.rank + 1) * per_process]
    batches = len(mine) // batch_size
    return [mine[i * batch_size : (i + 1) * batch_size].tolist() for i in range(batches)]


def load_model(path: str | Path, device: torch.device | str = "cpu") -> Matcher:
    """A `Matcher` with the weights and config of a checkpoint (``last.pt``, ``best.pt``)."""
    state = checkpoint.load(path, device)
    model = Matcher(MatcherConfig.from_dict(state["model_config"]))
    model.load_state_dict(state["model"])
    return model.to(device)


class Trainer:
    def __init__(
        self,
        model_config: MatcherConfig,
        config: TrainConfig,
        train_set: Any,
        val_set: Any = None,
        context: DistributedContext | None = None,
        resume: bool = False,
        progress: bool = True,
    ) -> None:
        self.config = config
        self.context = context or DistributedContext()
        self.device = resolve_device(config.device, self.context.local_rank)
        self.out = Path(config.out)
        self.train_set, self.val_set = train_set, val_set
        self.progress = progress and self.context.is_main
        if len(train_set) < config.batch_size * self.context.world_size:
            raise ValueError(
                f"{len(train_set)} training pairs are fewer than one batch of {config.batch_size} per process"
            )
        state, initial = None, None
        if resume and (self.out / LAST).is_file():
            state = checkpoint.load(self.out / LAST, "cpu")
            model_config = MatcherConfig.from_dict(state["model_config"])
        elif config.init is not None:
            initial = checkpoint.load(config.init, "cpu")
            model_config = MatcherConfig.from_dict(initial["model_config"])
        if config.no_reflectance:  # over the config of `init` too: fine-tuning a model into a range-only one
            model_config = dataclasses.replace(model_config, use_reflectance=False)
        torch.manual_seed(config.seed)
        self.model_config = model_config
        self.model: torch.nn.Module = Matcher(model_config).to(self.device)
        if initial is not None:
            self.model.load_state_dict(initial["model"])
        if self.context.enabled:
            # Before the optimiser: the conversion replaces the BatchNorm modules and their parameters.
            self.model = convert_batchnorm(self.model, self.device)
        self.optimizer: torch.optim.Optimizer
        if config.optimizer == "adam":
            self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        else:
            self.optimizer = torch.optim.SGD(
                self.model.parameters(), lr=config.lr, momentum=config.momentum, weight_decay=config.weight_decay
            )
        self.scheduler = torch.optim.lr_scheduler.StepLR(self.optimizer, config.lr_step_epochs, config.lr_gamma)
        self.epoch, self.step_in_epoch, self.global_step = 0, 0, 0
        self.best_metric = math.inf
        if state is not None:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.scheduler.load_state_dict(state["scheduler"])
            self.epoch, self.step_in_epoch = state["epoch"], state["step_in_epoch"]
            self.global_step = state["global_step"]
            self.best_metric = state.get("best_metric", state.get("best_epe", math.inf))
            checkpoint.set_rng_state(state["rng"])
        self.network: torch.nn.Module = self.model
        if self.context.enabled:
            self.network = DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None
            )
        if self.context.is_main:
            self.out.mkdir(parents=True, exist_ok=True)
            model_config.save(self.out / "model.json")
            config.save(self.out / "train.json")

    # -- checkpoints ---------------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "epoch": self.epoch,
            "step_in_epoch": self.step_in_epoch,
            "global_step": self.global_step,
            "best_metric": self.best_metric,
            "rng": checkpoint.rng_state(),
            "model_config": self.model_config.to_dict(),
            "train_config": self.config.to_dict(),
        }

    def save(self, name: str = LAST) -> None:
        if self.context.is_main:
            checkpoint.save_atomic(self.state(), self.out / name)

    # -- loop ----------------------------------------------------------------------------------------------

    def _loader(self, dataset: Any, batches: list[list[int]]) -> DataLoader:
        return DataLoader(
            dataset, batch_sampler=batches, collate_fn=collate, num_workers=self.config.workers,
            persistent_workers=False,
        )

    def train_step(self, batch: dict[str, torch.Tensor]) -> tuple[dict[str, float], FlowErrorSums]:
        self.network.train()
        batch = {key: value.to(self.device, non_blocking=True) for key, value in batch.items()}
        output = self.network(batch["ref"], batch["tgt"])
        loss, metrics = matching_loss(output, batch["flow"], batch["valid"], self.model_config)
        if self.config.pose_loss_weight > 0:
            pose, _ = pose_loss(output.flow, output.confidence, batch["flow"], batch["valid"], batch["pose_jacobian"])
            loss = loss + self.config.pose_loss_weight * pose
            metrics["pose_loss"] = float(pose.detach())
        if self.config.confidence_loss_weight > 0:
            confidence = confidence_loss(output.confidence, output.flow, batch["flow"], batch["valid"])
            loss = loss + self.config.confidence_loss_weight * confidence
            metrics["confidence_loss"] = float(confidence.detach())
        metrics["loss"] = float(loss.detach())
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        errors = FlowErrorSums()
        errors.add(output.flow.detach(), batch["flow"], batch["valid"])
        return metrics, errors

    def _stop(self) -> bool:
        return self.config.max_steps is not None and self.global_step >= self.config.max_steps

    def run(self) -> dict[str, Any]:
        """Trains until ``epochs`` (or ``max_steps``); returns the last epoch's log row."""
        from tqdm import tqdm

        row: dict[str, Any] = {}
        while self.epoch < self.config.epochs and not self._stop():
            self.train_set.set_epoch(self.epoch)
            batches = epoch_batches(len(self.train_set), self.config.batch_size, self.config.seed, self.epoch, self.context)
            remaining = batches[self.step_in_epoch :]
            errors, loss_sum, steps = FlowErrorSums(), 0.0, 0
            bar = tqdm(
                self._loader(self.train_set, remaining), total=len(batches), initial=self.step_in_epoch,
                desc=f"epoch {self.epoch + 1}/{self.config.epochs}", disable=not self.progress, dynamic_ncols=True,
            )
            for batch in bar:
                metrics, batch_errors = self.train_step(batch)
                errors.merge(batch_errors)
                loss_sum, steps = loss_sum + metrics["loss"], steps + 1
                self.step_in_epoch += 1
                self.global_step += 1
                bar.set_postfix(loss=f"{loss_sum / steps:.3f}", epe=f"{errors.epe:.2f}", fl=f"{errors.fl_all:.1f}%")
                if self._stop():
                    break
                if self.global_step % self.config.checkpoint_every == 0:
                    self.save()
            bar.close()
            if self.step_in_epoch < len(batches):  # stopped by max_steps inside the epoch
                self.save()
                break
            self.epoch, self.step_in_epoch = self.epoch + 1, 0
            self.scheduler.step()
            row = {"epoch": self.epoch, "step": self.global_step, "lr": self.optimizer.param_groups[0]["lr"],
                   "train_loss": loss_sum / max(steps, 1), "train_epe": errors.epe, "train_fl_all": errors.fl_all}
            if self.val_set is not None:
                val, val_pose = self.validate()
                row.update({"val_epe": val.epe, "val_fl_all": val.fl_all, "val_cells": val.cells})
                selection = val.epe if val.cells else math.nan
                if val_pose.pairs:
                    row.update({"val_rotation_mrad": val_pose.rotation, "val_translation_mm": val_pose.translation})
                    if self.config.pose_loss_weight > 0:
                        selection = val_pose.rotation
                if selection < self.best_metric:
                    self.best_metric = selection
                    self.save(BEST)
            self.save()
            if self.context.is_main:
                with open(self.out / "log.jsonl", "a") as log:
                    log.write(json.dumps(row) + "\n")
                if self.progress:
                    print(json.dumps(row))
        return row

    @torch.no_grad()
    def validate(self) -> tuple[FlowErrorSums, PoseErrorSums]:
        """EPE and Fl-all of the current weights over (up to ``val_max_pairs``, evenly spaced) held-out pairs,
        and the implied motion errors when the pairs carry pose Jacobians.

        Runs on the main process with the plain module (no collectives); the others wait.
        """
        errors, pose_errors = FlowErrorSums(), PoseErrorSums()
        if self.context.is_main:
            self.model.eval()
            size = len(self.val_set)  # type: ignore[arg-type]
            count = min(size, self.config.val_max_pairs)
            chosen = np.unique(np.linspace(0, size - 1, count).round().astype(int)).tolist()
            loader = self._loader(self.val_set, [[i] for i in chosen])
            for batch in loader:
                batch = {key: value.to(self.device) for key, value in batch.items()}
                output = self.model(batch["ref"], batch["tgt"])
                errors.add(output.flow, batch["flow"], batch["valid"])
                if "pose_jacobian" in batch:
                    _, pose = pose_loss(output.flow, output.confidence, batch["flow"], batch["valid"], batch["pose_jacobian"])
                    pose_errors.add(pose)
            self.model.train()
        if self.context.enabled:
            torch.distributed.barrier()
        return errors, pose_errors
