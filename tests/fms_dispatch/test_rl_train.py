"""``fms train`` (fms_dispatch.rl.train): what a user meets on the way to a model — refusals before any work,
progress on long phases."""

from __future__ import annotations

import pytest

pytest.importorskip("sb3_contrib")

from fms_dispatch.rl.train import train  # noqa: E402

#: a tiny run on generated BU-size shops (no benchmark instance, so no allow_benchmarks)
TINY = {"train": ["genbu:1*2@11"], "padding": "bu", "n_envs": 1, "vec_env": "dummy", "eval_freq": 64,
        "save_freq": 64, "hidden": 16, "ppo": {"n_steps": 64, "batch_size": 32, "n_epochs": 1}}


@pytest.mark.parametrize("ppo, n_envs, needle", [
    ({"n_steps": 64, "batch_size": 1}, 1, "ppo.batch_size must be >= 2"),
    ({"n_steps": 65, "batch_size": 64}, 1, "n_steps x n_envs = 65 x 1 = 65 steps in mini-batches of ppo.batch_size "
                                          "64 leaves a last mini-batch of one step"),
    ({"n_steps": 32, "batch_size": 21}, 2, "= 32 x 2 = 64 steps in mini-batches of ppo.batch_size 21"),
])
def test_a_mini_batch_of_one_step_is_refused_before_any_work(tmp_path, ppo, n_envs, needle):
    """PPO normalises each mini-batch's advantages by their standard deviation: one step made the losses NaN and
    the run ended in "PPO diverged ... lower ppo.learning_rate", after its warm start, which sent the user to the
    wrong knob."""
    out = tmp_path / "m"
    cfg = dict(TINY, steps=128, n_envs=n_envs, ppo=dict(TINY["ppo"], **ppo),
               warm_start={"expert": "rules", "epochs": 1})
    with pytest.raises(ValueError, match=needle.replace("(", r"\(").replace(")", r"\)")):
        train(cfg, out, progress=False, tensorboard=tmp_path / "tb")
    assert not out.exists()  # refused before the warm start, and before the folder was made


def test_ppo_says_how_far_it_is_where_no_progress_bar_is_drawn(tmp_path, capsys):
    """sb3's bar is drawn only on a terminal; in a log file the PPO phase said nothing between the warm start and
    the final line (hours on a real run). Now progress lines go to stderr, about 20 a run, after whole rollouts."""
    train(dict(TINY, steps=256, warm_start={"expert": "rules", "epochs": 1}), tmp_path / "m", progress=True,
          tensorboard=tmp_path / "tb")
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("PPO: ")]
    assert [x.split(",")[0] for x in lines] == [f"PPO: {n}/256 steps ({100 * n // 256} %)" for n in (64, 128, 192, 256)]
    assert all("best eval mean reward" in x for x in lines)  # the warm start was evaluated: PPO must beat it


def test_no_progress_means_no_ppo_lines(tmp_path, capsys):
    train(dict(TINY, steps=128), tmp_path / "m", progress=False, tensorboard=tmp_path / "tb")
    assert "PPO: " not in capsys.readouterr().err


def test_resume_refuses_a_config_edited_to_train_on_a_benchmark(tmp_path):
    """The training/test separation was checked on fresh runs only: a config.json edited to train on EX12 was
    resumed on it, and the model's record (allow_benchmarks false) still said it had trained apart."""
    import json

    out = tmp_path / "m"
    train(dict(TINY, steps=64), out, progress=False, tensorboard=tmp_path / "tb")
    saved = json.loads((out / "config.json").read_text())
    (out / "config.json").write_text(json.dumps(dict(saved, train=["EX12"])))
    with pytest.raises(ValueError, match=f"cannot resume: {out / 'config.json'}: training must use generated shops "
                                         "only .*'EX12' gives EX12"):
        train({"steps": 64}, out, resume=True, progress=False, tensorboard=tmp_path / "tb")
    (out / "config.json").write_text(json.dumps(dict(saved, train=["EX12"], allow_benchmarks=True)))
    assert train({"steps": 64}, out, resume=True, progress=False, tensorboard=tmp_path / "tb")["ppo_steps"] == 128


def test_an_interrupt_in_the_warm_start_says_nothing_was_kept(tmp_path, capsys, monkeypatch):
    """Ctrl-C or SIGTERM in the cloning said only "fms: interrupted", after what may have been hours of
    demonstrations: now it says that no weights were saved and that a new run into the folder starts over."""
    from fms_dispatch.cli import main
    from fms_dispatch.rl import imitation

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(imitation, "clone", interrupted)
    out = tmp_path / "m"
    args = ["train", "genbu:1*2@11", "--padding", "bu", "--n-envs", "1", "--steps", "64", "--out", str(out),
            "--no-progress", "--tensorboard", str(tmp_path / "tb")]
    config = tmp_path / "c.json"
    config.write_text('{"warm_start": {"expert": "rules", "epochs": 1}}')
    assert main(args + ["--config", str(config)]) == 130
    assert (f"fms: interrupted before the first weights were saved (in the warm start): nothing was kept; a new run "
            f"into {out} starts over") in capsys.readouterr().err
    assert list(out.iterdir()) == []
