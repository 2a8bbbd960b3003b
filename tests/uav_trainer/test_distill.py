"""distill: one network trained to act as an ensemble does."""

import json

import numpy as np
import pytest
import torch

from conftest import ROOT
from uav_policy import weights as wio
from uav_policy.networks import NetConfig, QEnsemble, build_network
from uav_trainer import distill


class Bands(torch.nn.Module):
    """A constructed ensemble member: action a's Q is the mean depth of the a-th quarter of the newest frame's columns (fly
    where it is far), plus this member's bias on each action; three members' mean is the ensemble."""

    def __init__(self, bias):
        super().__init__()
        self.bias = torch.tensor(bias)

    def forward(self, x):
        bands = torch.nan_to_num(x[:, -1], posinf=10.0).clamp(max=10.0).unflatten(2, (4, -1)).mean(dim=(1, 3))
        return bands + self.bias, None


class Mean(torch.nn.Module):
    def __init__(self, members):
        super().__init__()
        self.members = torch.nn.ModuleList(members)

    def forward(self, x):
        return torch.stack([m(x)[0] for m in self.members]).mean(0), None


def test_a_student_fitted_to_an_ensemble_agrees_with_it_on_held_out_states():
    """A constructed task: three networks that each prefer the farthest quarter of the view, biased differently, as
    one ensemble; each quarter of the view at a random depth. The student (a small CNN) fitted on 600 states acts as
    the ensemble on held-out states (measured: 0.24 before, 0.98 after)."""
    cfg = NetConfig(model="cnn", height=32, width=32, conv_channels=(8, 16), cnn_hidden=32, head_hidden=16)
    ensemble = Mean([Bands(b) for b in ([0.5, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 0, 0.3])]).eval()
    rng = np.random.default_rng(0)

    def states(n):  # each quarter of the view at its own depth, with noise
        bands = np.repeat(rng.uniform(1.0, 9.0, (n, 1, 1, 4)), 8, axis=3)
        return (bands + rng.normal(0.0, 0.1, (n, cfg.frames, 32, 32))).astype(np.float32)

    train, held_out = states(600), states(300)
    student = build_network(cfg, seed=9)
    t_train, t_held = distill.q_of(ensemble, train), distill.q_of(ensemble, held_out)
    before = distill.agreement(student, t_held, held_out)
    distill.fit(student, train, t_train, epochs=30, batch=32, lr=3e-3, rng=np.random.default_rng(0))
    after = distill.agreement(student, t_held, held_out)
    assert after >= 0.9 and after > before + 0.3, (before, after)


def ensemble_files(tmp_path, model="cnn", cameras=(90.0, 90.0), seeds=(1, 2)):
    files = []
    for seed, camera in zip(seeds, cameras, strict=True):
        path = tmp_path / f"{model}_{seed}_{camera:g}.safetensors"
        cfg = NetConfig(model=model)
        wio.save_file(build_network(cfg, seed=seed), cfg, path, camera, 0.2)
        files.append(str(path))
    return files


def test_distill_writes_one_network_naming_its_ensemble_and_is_seeded(tmp_path, capsys):
    files = ensemble_files(tmp_path)
    outs = []
    threads = torch.get_num_threads()
    try:
        for k in (0, 1):
            out = tmp_path / f"student{k}.safetensors"
            args = ["--ensemble", *files, "--recipe", "paper", "--params-dir", str(ROOT / "params"), "--out", str(out)]
            assert distill.main([*args, "--rounds", "2", "--steps-per-round", "40", "--epochs", "1"]) == 0
            outs.append(out)
    finally:
        torch.set_num_threads(threads)
    assert outs[0].read_bytes() == outs[1].read_bytes(), "the same ensemble, recipe and seed: the same student"
    printed = capsys.readouterr().out
    assert "round 2/2 (student flying, 80 states" in printed and "one network for 2 ensemble files" in printed
    sources = json.loads(wio.read_file_notes(outs[0])[wio.DISTILLED_KEY])
    assert [t["file"] for t in sources] == [f.split("/")[-1] for f in files] and all(len(t["sha256"]) == 64 for t in sources)
    assert wio.read_file_camera(outs[0]) == 90.0 and wio.read_file_window(outs[0]) == 0.2
    net = wio.load_file(outs[0], wio.read_file_config(outs[0]))
    assert not isinstance(net, QEnsemble)


def test_a_mixed_ensemble_is_refused_naming_why(tmp_path, capsys):
    args = ["--recipe", "paper", "--params-dir", str(ROOT / "params"), "--out", str(tmp_path / "s.safetensors")]
    mixed = ensemble_files(tmp_path, "cnn", (90.0,), (1,)) + ensemble_files(tmp_path, "sam", (90.0,), (2,))
    with pytest.raises(SystemExit):
        distill.main(["--ensemble", *mixed, *args])
    assert "an ensemble of mixed architectures (cnn, sam" in capsys.readouterr().err
    cameras = ensemble_files(tmp_path, "cnn", (90.0, 87.0), (3, 4))
    with pytest.raises(SystemExit):
        distill.main(["--ensemble", *cameras, *args])
    assert "an ensemble trained behind different cameras" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        distill.main(["--ensemble", *ensemble_files(tmp_path, "cnn", (150.0,), (5,)), *args])
    assert "give the recipe they were trained with" in capsys.readouterr().err
