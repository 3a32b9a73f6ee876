"""Where the main job's learned rows come from: two sources with one interface.

- ``ShippedModels`` (the default, ``--models=DIR``): the hub-format model directories named
  ``pdpo_<task>_h<H>`` and ``crowdnavpp_<task>``; nothing is trained, each card says how its model
  was made, and the report lists the models it did not find.
- ``TrainedFromScratch`` (``--models=null``, the recipes): the ``Training`` stages with the
  config's budget, then the hub-format pushes of what they made.

Both give the rows after the baselines (``rows``), the PDPO policy the figures draw
(``figure_policy``), the learning curves (``curves``: (caption, image) and how to draw them), what
to publish once evaluated (``publish``), the missing models and the budget the report shows.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

from ..checkpoint_files import POLICY_CONFIG, WEIGHTS
from ..evaluation.report import Budget, Stage
from .config import MainConfig
from .evaluation import Curve
from .paths import SHORT, RunPaths
from .rows import CROWDNAVPP_LABEL, FINETUNED_LABEL, Evaluation, MethodRow, finetuned_label
from .training import Training


class Source:
    """The interface of a source of rows (see the module docstring)."""

    models: Path | None = None  # the model directory the report names (None: trained by this run)
    redraw: bool = False  # redraw the figures on every run (the policies may have changed)

    def rows(self, task: str) -> list[MethodRow]:
        raise NotImplementedError

    def figure_policy(self, task: str) -> Evaluation | None:
        raise NotImplementedError

    def curves(self, task: str) -> tuple[list[Curve], Callable[[], None]]:
        raise NotImplementedError

    def publish(self, task: str) -> None:
        """After the rows are evaluated: push what was made (nothing by default)."""

    def missing(self, task: str) -> list[str]:
        return []

    def budget(self) -> Budget | None:
        return None


class ShippedModels(Source):
    """Trained models in ``cfg.models``: found, evaluated, drawn; never trained."""

    redraw = True

    def __init__(self, cfg: MainConfig, paths: RunPaths):
        self.cfg = cfg
        self.paths = paths
        self.models = cfg.models
        self._found: dict[str, list[tuple[str, Evaluation]]] = {}

    def names(self, task: str) -> dict[str, str]:
        """Row label -> the model directory's name, for every policy the job can show."""
        short = SHORT[task]
        return {FINETUNED_LABEL[1]: f"pdpo_{short}_h1", FINETUNED_LABEL[5]: f"pdpo_{short}_h5",
                CROWDNAVPP_LABEL: f"crowdnavpp_{short}"}

    def found(self, task: str) -> list[tuple[str, Evaluation]]:
        """The shipped models of ``task`` that exist in ``--models``, (label, evaluation) (read once
        per run: the rows, the figures and the curves all ask)."""
        if task not in self._found:
            found = []
            for label, name in self.names(task).items():
                path = self.models / name
                if (path / WEIGHTS).exists():
                    config = json.loads((path / POLICY_CONFIG).read_text())
                    horizon = config["horizon"] if config.get("type") == "pdpo" else None
                    if horizon is not None and not name.endswith(f"_h{horizon}"):
                        raise ValueError(f"{path} holds a PDPO policy with H = {horizon}: its row ({label}) needs H = "
                                         f"{name.rsplit('_h', 1)[-1]}")
                    found.append((label, Evaluation(name, path, horizon, shipped=True)))
            self._found[task] = found
        return self._found[task]

    def rows(self, task: str) -> list[MethodRow]:
        return [MethodRow(label, [ev]) for label, ev in self.found(task)]

    def figure_policy(self, task: str) -> Evaluation | None:
        """H = 5 when it is shipped, else another PDPO policy."""
        pdpo = sorted((ev for _, ev in self.found(task) if ev.horizon is not None), key=lambda ev: ev.horizon != 5)
        return pdpo[0] if pdpo else None

    def curves(self, task: str) -> tuple[list[Curve], Callable[[], None]]:
        """Each shipped model's learning curve, copied from its card."""
        from ..data.hub import CURVE_FILE

        out = self.paths.figures_dir(task)
        copies = [(ev.policy / CURVE_FILE, out / f"curve_{ev.name}.png", label)
                  for label, ev in self.found(task) if (ev.policy / CURVE_FILE).exists()]
        curves = [(f"{label}: the learning curve from its model card (`{src.parent.name}`).", dst) for src, dst, label in copies]

        def draw() -> None:
            for src, dst, _ in copies:
                shutil.copyfile(src, dst)

        return curves, draw

    def missing(self, task: str) -> list[str]:
        shown = {label for label, _ in self.found(task)}
        return [name for label, name in self.names(task).items() if label not in shown]


class TrainedFromScratch(Source):
    """Every policy trained by this run with ``cfg``'s budget (``Training``), then pushed."""

    def __init__(self, cfg: MainConfig, training: Training):
        self.cfg = cfg
        self.training = training

    def rows(self, task: str) -> list[MethodRow]:
        """Demonstrations, then each PDPO policy's pretraining and fine-tuning stages and each
        CrowdNav++ PPO run, seed by seed; the rows: BC only (the main horizon), each horizon
        fine-tuned, CrowdNav++."""
        t, c = self.training, self.cfg
        if c.horizons:
            t.collect(task)
        trained: dict[tuple[int, int], tuple[Stage, Stage]] = {}
        crowdnavpp: dict[int, Stage] = {}
        for seed in c.seeds:
            for h in c.horizons:
                pretrain = t.pretrain(task, h, seed)
                trained[h, seed] = (pretrain, [t.finetune(task, h, seed, n) for n in t.ft_stages][-1])
                if c.select_top:
                    t.select(task, h, seed)
            if c.crowdnavpp_env_steps:
                crowdnavpp[seed] = t.train_crowdnavpp(task, seed)
                if c.select_top:
                    t.select(task, None, seed)
        rows = []
        h0 = t.main_horizon
        if h0 is not None:
            rows.append(MethodRow(f"PDPO pretrained only (H = {h0}, BC)",
                                  [t.pretrained(task, h0, s, trained[h0, s][0]) for s in c.seeds]))
        for h in sorted(c.horizons):
            rows.append(MethodRow(finetuned_label(h), [t.finetuned(task, h, s, *trained[h, s]) for s in c.seeds]))
        if c.crowdnavpp_env_steps:
            rows.append(MethodRow(CROWDNAVPP_LABEL, [t.crowdnavpp(task, s, crowdnavpp[s]) for s in c.seeds]))
        return rows

    def figure_policy(self, task: str) -> Evaluation | None:
        h = self.training.main_horizon
        return None if h is None else self.training.finetuned(task, h, self.cfg.seeds[0])

    def curves(self, task: str) -> tuple[list[Curve], Callable[[], None]]:
        """This run's fine-tuning curves, every horizon (and stage) on one figure."""
        from ..measure.plots import plot_finetune_curves

        image = self.training.paths.figures_dir(task) / "finetune_curves.png"
        caption = ("Fine-tuning: training success rate and average episode reward against environment steps "
                   "(lines: training episodes, smoothed; markers: deterministic validation).")

        def draw() -> None:
            runs = {}
            for h in sorted(self.cfg.horizons, reverse=True):
                runs.update(self.training.finetune_records(task, h, self.cfg.seeds[0],
                                                           finetuned_label(h).replace(", fine-tuned", "")))
            plot_finetune_curves(runs, image)

        return [(caption, image)], draw

    def publish(self, task: str) -> None:
        self.training.push(task)

    def budget(self) -> Budget:
        c = self.cfg
        return Budget(c.run, c.preset, c.demos, c.bc_steps, c.bc_epochs, c.bc_batch_size, c.ft_env_steps, list(c.seeds),
                      c.test_episodes, c.crowdnavpp_env_steps, c.ft2_env_steps, c.ft2_from)
