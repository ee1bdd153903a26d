"""How much the images can say about the concentration, from below: a classifier trained
directly to tell a CDM scene at ``a_low`` from the same scene at ``a_high``
(docs/notebook; the summary's concentration contrast is the bound from above).

Independent draws per class (each class its own seed), ``--n`` images per class, the
estimator's own inputs (``training.inputs`` transform, whitening over the training part,
the 1.5 θ_E mask) and the reduced ResNet with one logit (the campaign's trunk, no γ
input), trained with binary cross-entropy under the eight grid symmetries. Sets of 13
images (the scene's ``images_per_set``) are held out whole (``--heldout`` of them). On the
held-out sets it reports the per-image AUC, ``ln 2 − BCE`` (nats of information about
the class per image; 0 = none), and the AUC of whole sets (13-image stacks) scored by the sum
of their logits (what a stack of 13 lenses could tell). Prints one JSON record and writes it to
``--out``.

    OMP_NUM_THREADS=1 .venv/bin/python studies/concentration_classifier.py \\
        --scene nfw_ref --n 2002 --out results/studies/classifier_nfw_ref.json
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from subslope import config as cfgmod
from subslope.io.atomic import write_text
from subslope.nre.models import PRESETS, ResNetTrunk
from subslope.nre.preprocess import preprocess
from subslope.simulation.shard import simulate_images
from subslope.stages.train import input_transform


def simulate_class(config, scene: str, n: int, a: float, seed: int, k: int) -> dict:
    """``n`` images of ``scene`` at multiplier ``a``, their own draws (seed, class k)."""
    out = simulate_images(config, scene, n, np.random.SeedSequence([seed, k]), multiplier=a)
    p = out["params"]
    return {
        "images": out["images"],
        "theta_e": p["theta_e"],
        "lens_x": p["lens_x"],
        "lens_y": p["lens_y"],
        "set_index": p["set_index"] + 100000 * k,
    }


def model_inputs(data: dict, transform, white, pixel_scale: float, mask: float) -> torch.Tensor:
    """The estimator's view of the images: transform, whitening, θ_E mask; ``(n, 1, H, W)``."""
    x = torch.from_numpy(transform.apply(data["images"]))
    t = {k: torch.as_tensor(data[k], dtype=torch.float32) for k in ("theta_e", "lens_x", "lens_y")}
    x = preprocess(
        x, t["theta_e"], t["lens_x"], t["lens_y"], *white, pixel_scale=pixel_scale, mask_factor=mask
    )
    return x.unsqueeze(1).float()


class Classifier(nn.Module):
    """The campaign's reduced ResNet trunk and a linear layer to one logit."""

    def __init__(self):
        super().__init__()
        arch = PRESETS["reduced"]
        self.trunk = ResNetTrunk(arch["depth"], arch["width"], arch["stem"])
        self.head = nn.Linear(self.trunk.out_features, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.trunk(x)).squeeze(1)


def dihedral(x: torch.Tensor, k: int) -> torch.Tensor:
    """View ``k`` (0..7) of the eight rotations and reflections of the pixel grid."""
    x = torch.rot90(x, k % 4, dims=(-2, -1))
    return torch.flip(x, dims=(-1,)) if k >= 4 else x


def auc(score: np.ndarray, label: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney U / n₀n₁, ties counted half)."""
    from scipy.stats import rankdata

    r = rankdata(score)
    n1 = int(label.sum())
    n0 = label.size - n1
    return float((r[label == 1].sum() - n1 * (n1 + 1) / 2) / (n0 * n1))


def train(x, y, epochs: int, seed: int, batch: int = 64, lr: float = 1e-3) -> Classifier:
    """AdamW on binary cross-entropy, each batch under one random grid symmetry."""
    torch.manual_seed(seed)
    model = Classifier()
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-2)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    loss_fn = nn.BCEWithLogitsLoss()
    gen = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        model.train()
        order = torch.randperm(len(y), generator=gen)
        for i in range(0, len(y), batch):
            idx = order[i : i + batch]
            if idx.numel() < 2:
                continue
            k = int(torch.randint(8, (1,), generator=gen))
            loss = loss_fn(model(dihedral(x[idx], k)), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    return model


@torch.no_grad()
def logits(model: Classifier, x: torch.Tensor) -> np.ndarray:
    """Logits averaged over the eight grid symmetries, as the estimator averages ln r."""
    model.eval()
    out = [
        torch.cat([model(dihedral(x[i : i + 256], k)) for i in range(0, len(x), 256)])
        for k in range(8)
    ]
    return torch.stack(out).mean(0).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--resources", default=None, help="data.resources_dir (default: config's)")
    ap.add_argument("--scene", default="nfw_ref")
    ap.add_argument("--a-low", type=float, default=1.0)
    ap.add_argument("--a-high", type=float, default=8.0)
    ap.add_argument("--n", type=int, default=2002, help="images per class (multiple of 13)")
    ap.add_argument("--heldout", type=float, default=0.25, help="fraction of sets held out")
    ap.add_argument("--epochs", type=int, default=15)
    ap.add_argument("--seed", type=int, default=20231207)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--inputs", default=None, help="training.inputs (default: config's)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    config = cfgmod.load(args.config, env=False)
    if args.resources:
        config["data"]["resources_dir"] = args.resources
    if args.inputs:
        config["training"]["inputs"] = args.inputs
    config = cfgmod.validate(config)
    if config["training"]["inputs"] == "light_subtracted":
        ap.error("training.inputs = light_subtracted needs lens-light fits; pass --inputs snr")
    t0 = time.perf_counter()
    classes = [
        simulate_class(config, args.scene, args.n, a, args.seed, k)
        for k, a in enumerate((args.a_low, args.a_high))
    ]
    t_sim = time.perf_counter() - t0
    data = {key: np.concatenate([c[key] for c in classes]) for key in classes[0]}
    y = np.repeat([0.0, 1.0], args.n).astype(np.float32)
    sets = np.unique(data["set_index"])
    rng = np.random.default_rng(args.seed)
    held_sets = rng.choice(sets, int(round(args.heldout * sets.size)), replace=False)
    held = np.isin(data["set_index"], held_sets)
    transform = input_transform(config)
    train_px = transform.apply(data["images"][~held])
    white = (float(train_px.mean()), float(train_px.std()))
    inst = config["instrument"]
    x = model_inputs(data, transform, white, inst["pixel_scale"], config["training"]["mask_factor"])
    yt = torch.from_numpy(y)
    t1 = time.perf_counter()
    model = train(x[~held], yt[~held], args.epochs, args.seed)
    t_train = time.perf_counter() - t1
    s = logits(model, x[held])
    yh = y[held]
    p = 1.0 / (1.0 + np.exp(-s))
    bce = float(-np.mean(yh * np.log(p + 1e-12) + (1 - yh) * np.log(1 - p + 1e-12)))
    set_ids = data["set_index"][held]
    stack_ids = np.unique(set_ids)
    stack_score = np.array([s[set_ids == i].sum() for i in stack_ids])
    stack_label = np.array([yh[set_ids == i][0] for i in stack_ids])
    record = {
        "scene": args.scene,
        "a_low": args.a_low,
        "a_high": args.a_high,
        "n_per_class": args.n,
        "heldout_images": int(held.sum()),
        "heldout_stacks": int(stack_ids.size),
        "auc_image": auc(s, yh),
        "info_nats_image": math.log(2.0) - bce,
        "stack_size": int(np.bincount(np.unique(set_ids, return_inverse=True)[1]).max()),
        "auc_stack": auc(stack_score, stack_label),
        "epochs": args.epochs,
        "seed": args.seed,
        "simulate_s": round(t_sim, 1),
        "train_s": round(t_train, 1),
    }
    text = json.dumps(record, indent=1)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, text + "\n")


if __name__ == "__main__":
    main()
