"""``pretraining.detection_gaps = "auto"``: the candidate that predicts the orchard validation
recording better is chosen (the smaller on a tie), the choice is cached, and the windows are
scored as ``evaluate`` scores them."""

from dataclasses import replace

import pytest
import torch

from dronefl.config import load_scenario
from dronefl.experiments import gap_choice
from dronefl.experiments.gap_choice import (
    GapChoice,
    choose_detection_gaps,
    resolve_gaps,
    validation_dir,
    window_errors,
    window_set,
)
from dronefl.experiments.pretrain import PretrainSpec, pretrained_state
from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
from dronefl.models.model import build_model
from dronefl.models.train import evaluate
from dronefl.models.windows import FEATURE_DIM
from dronefl.serialize import ResultError
from dronefl.settings import Setting

CASE1 = load_scenario("case1")


def _spec(gaps: str = "auto") -> PretrainSpec:
    """Case 1 with a 40 s validation recording (the recording is as long as the crop field's)."""
    setting = Setting.load(
        "recommended", ["pretraining.seconds=40", f"pretraining.detection_gaps={gaps}"]
    )
    return PretrainSpec(CASE1, setting, "dronefl")


def _place(state: dict[str, torch.Tensor], spec: PretrainSpec, folder) -> None:
    settings = spec.settings(folder)
    checkpoint = Checkpoint("dronefl", settings.rounds, state, [])
    save_checkpoint(settings.checkpoint_path, settings.history_path, checkpoint)


def _models(quick_pretrained) -> tuple[dict, dict]:
    """The quick pretrained model and an untrained one (far worse)."""
    quick = PretrainSpec(CASE1, Setting.load("recommended"), "dronefl")
    good = pretrained_state(quick, quick_pretrained, progress=False)
    return good, build_model(quick.model, seed=3).state_dict()


def test_the_better_candidate_is_chosen_the_smaller_on_a_tie_and_the_choice_is_cached(
    tmp_path, quick_pretrained, monkeypatch
):
    good, bad = _models(quick_pretrained)
    spec = _spec()
    for folder, (at_0, at_3), chosen in (
        (tmp_path / "a", (good, bad), 0.0),
        (tmp_path / "b", (bad, good), 0.3),
        (tmp_path / "c", (good, good), 0.0),  # equal: the smaller
    ):
        _place(at_0, replace(spec, detection_gaps=0.0), folder)
        _place(at_3, replace(spec, detection_gaps=0.3), folder)
        choice = choose_detection_gaps(spec, folder, progress=False)
        assert choice.chosen == chosen
        assert set(choice.mse) == {0.0, 0.3}
        assert resolve_gaps(spec, folder, progress=False).detection_gaps == chosen
    assert choice.mse[0.0] == choice.mse[0.3]
    # Cached: no recording or scoring again, and what was saved is what was chosen.
    monkeypatch.setattr(gap_choice, "simulate", lambda *a, **k: pytest.fail("re-recorded"))
    assert choose_detection_gaps(spec, tmp_path / "b", progress=False) == GapChoice.load(
        GapChoice.path(spec, tmp_path / "b", gap_choice.GAP_CANDIDATES)
    )
    assert resolve_gaps(_spec("0.15"), tmp_path).detection_gaps == 0.15
    corrupt = GapChoice.path(spec, tmp_path / "a", gap_choice.GAP_CANDIDATES)
    corrupt.write_text('{"chosen": 0.3')
    with pytest.raises(ResultError, match="not a detection-gap choice"):
        choose_detection_gaps(spec, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="ascending"):
        choose_detection_gaps(spec, tmp_path, candidates=(0.3, 0.0))


def test_every_validation_window_is_scored_once_as_evaluate_scores_it(tmp_path, quick_pretrained):
    good, _ = _models(quick_pretrained)
    spec = _spec()
    _place(good, spec, tmp_path)
    _place(good, replace(spec, detection_gaps=0.3), tmp_path)
    choose_detection_gaps(spec, tmp_path, progress=False)  # records the validation flight
    data = window_set(validation_dir(spec, tmp_path), spec, tmp_path)
    errors = window_errors(good, spec, data)

    assert data.labels.shape[1:] == (1, 2) and errors.shape == (len(data),)
    model = build_model(spec.model)
    model.load_state_dict(good)
    assert errors.mean() == pytest.approx(evaluate(model, data), rel=1e-5)
    # The validation flight is in the orchard, whose trees leave windows with gaps.
    counts = (data.features[..., FEATURE_DIM - 1] > 0.5).sum(1)
    assert counts.min() < 10 and counts.max() == 10
