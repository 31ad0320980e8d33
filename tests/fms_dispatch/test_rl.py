"""The PPO dispatcher: fast features, training (tiny), resume, inference, shipped models, errors."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("sb3_contrib")

from fms_dispatch.rl import add_train_parser, ppo_solver  # noqa: E402
from fms_dispatch.rl.envs import padding_for  # noqa: E402
from fms_dispatch.rl.models import SHIPPED, default_model_name, models_dir, resolve_model  # noqa: E402
from fms_dispatch.rl.train import expand_instances, train  # noqa: E402
from fms_sim.benchmarks import builtin  # noqa: E402
from fms_sim.validate import validate  # noqa: E402

# mechanics tests may train on benchmark instances; shipped models may not (test_shipped_models_train_apart)
TINY = {"n_envs": 1, "vec_env": "dummy", "eval_freq": 128, "save_freq": 128, "hidden": 16, "allow_benchmarks": True,
        "ppo": {"n_steps": 128, "batch_size": 64, "n_epochs": 1}}


def test_padding_profiles():
    assert padding_for("large", []) == dict(max_jobs=100, max_machines=20, max_tools=20, max_agvs=10, max_tts=5)
    assert padding_for("auto", [builtin("EX72")]) == dict(max_jobs=8, max_machines=4, max_tools=0, max_agvs=2,
                                                          max_tts=0)
    with pytest.raises(ValueError, match="unknown padding profile"):
        padding_for("huge", [])


def test_expand_instances():
    names = [i.name for i in expand_instances(["EX?2", "EX102"])]
    assert names == [f"EX{s}2" for s in range(1, 11)]
    gen = expand_instances(["gen:5x3x3*2@7"])
    assert [(i.n_jobs, i.n_machines, i.n_agvs, i.n_tool_transporters) for i in gen] == [(5, 3, 10, 5)] * 2
    assert gen[0].jobs != gen[1].jobs
    assert not expand_instances(["gen:5x3x3*1@7"], {"no_tools": True})[0].has_tools
    assert [i.n_agvs for i in expand_instances(["EX12"], {"agvs": 3})] == [3]
    with pytest.raises(ValueError, match="matches no built-in"):
        expand_instances(["zz*"])


def test_tiny_training_saves_reloads_solves_and_resumes(tmp_path):
    out = tmp_path / "tiny"
    cfg = dict(TINY, train=["EX12"], steps=256, seed=5, padding="bu")
    m = train(cfg, out, progress=False, tensorboard=tmp_path / "tb")
    assert m["training"]["timesteps"] == 256
    for f in ("config.json", "model.zip", "best_model.zip", "metrics.json"):
        assert (out / f).is_file(), f
    saved = json.loads((out / "config.json").read_text())
    assert saved["train"] == ["EX12"] and saved["reward"] == "shaped" and saved["padding"] == "bu"
    assert any((tmp_path / "tb").iterdir())  # TensorBoard logs written

    inst = builtin("EX12")
    solve = ppo_solver(f"ppo:{out}")
    s1, s2 = solve(inst), solve(inst)
    assert validate(inst, s1) == []
    assert s1.to_dict() == s2.to_dict()  # deterministic
    assert s1.makespan == m["training"]["eval_makespan"]["EX12"]
    assert s1.meta["solver"] == "ppo:tiny" and s1.meta["lookahead"] is False

    # training exported the numpy actor; it computes the torch policy's logits
    from fms_dispatch.rl.agent import Agent
    from fms_dispatch.rl.models import load_agent
    from fms_sim.shop import Shop

    assert (out / "best_model.actor.npz").is_file() and (out / "model.actor.npz").is_file()
    agent = load_agent(str(out))
    assert not agent.uses_torch
    ref = Agent(agent.path, agent.padding, torch=True)
    assert ref.uses_torch
    shop = Shop(builtin("EX42"))
    while not shop.done:
        fast, mask = agent.logits(shop, fast=True)
        slow, _ = ref.logits(shop, fast=False)
        assert np.array_equal(np.isfinite(fast), mask) and np.allclose(fast[mask], slow[mask], atol=1e-5)
        shop.act(agent.act(shop))
    with pytest.raises(ValueError, match="loaded without torch"):
        agent.logits(shop, fast=False)

    m2 = train({"steps": 128}, out, resume=True, progress=False, tensorboard=tmp_path / "tb")
    assert m2["training"]["timesteps"] == 384  # continued, not restarted
    assert m2["resumes"] == [{"ppo_steps_before": 256, "ppo_steps_after": 384, "dagger_rounds": 0,
                              "wall_seconds": m2["resumes"][0]["wall_seconds"], "interrupted": False}]
    assert json.loads((out / "metrics.json").read_text())["resumes"] == m2["resumes"]

    # figures measured on the solving weights go when a resume replaces them, and stay when it does not (a resume
    # kept the held-out results of weights it had replaced)
    def resume_against(best: float) -> dict:
        m = json.loads((out / "metrics.json").read_text())
        m["heldout"] = {"shops": {"ho00": {"ppo": 1}}}
        m["plan_assignments"] = {"assignments": 5, "network_otherwise": 0}  # (the network was checked)
        m["training"]["best_mean_reward"] = best
        (out / "metrics.json").write_text(json.dumps(m))
        return train({"steps": 128}, out, resume=True, progress=False, tensorboard=tmp_path / "tb")

    before = (out / "best_model.zip").read_bytes()
    kept = resume_against(1e9)
    assert "heldout" in kept and "plan_assignments" in kept and (out / "best_model.zip").read_bytes() == before
    replaced = resume_against(-1e9)  # none beats it above; here the resume's weights do
    assert "heldout" not in replaced and "plan_assignments" not in replaced
    assert (out / "best_model.zip").read_bytes() != before

    # a new model is not trained over this one (it kept the old best_model.zip and reported it as its own) ...
    again = dict(TINY, train=["EX12"], steps=128, seed=6, padding="bu", eval_freq=10_000)  # no evaluation: no best
    with pytest.raises(ValueError, match=r"already holds a model \(config.json, metrics.json, model.zip, "
                                         r"best_model.zip, .*--force to replace it"):
        train(again, out, progress=False, tensorboard=tmp_path / "tb")
    with pytest.raises(ValueError, match="give one"):
        train({"steps": 128}, out, resume=True, force=True, progress=False)
    # ... unless forced: the old model's files are gone, the new run's weights are its own
    m3 = train(again, out, progress=False, tensorboard=tmp_path / "tb", force=True)
    assert m3["training"]["timesteps"] == 128 and m3["training"]["weights"] == "model.zip" and "resumes" not in m3
    assert not (out / "best_model.zip").exists() and not (out / "best_model.actor.npz").exists()
    assert json.loads((out / "config.json").read_text())["seed"] == 6


def test_an_interrupted_training_says_so_and_exits_130(tmp_path, capsys, monkeypatch):
    """Ctrl-C in PPO keeps the model (--resume continues it), but fms train exited 0 without a word: only
    metrics.json said it was interrupted."""
    from sb3_contrib import MaskablePPO

    from fms_dispatch.cli import main

    def stop(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(MaskablePPO, "learn", stop)
    out = tmp_path / "m"
    assert main(["train", "EX12", "--allow-benchmarks", "--padding", "bu", "--n-envs", "1", "--steps", "128",
                 "--out", str(out), "--no-progress"]) == 130
    err = capsys.readouterr().err
    assert f"fms: interrupted: the model is saved at 0 steps; fms train --out {out} --resume --steps N" in err
    assert json.loads((out / "metrics.json").read_text())["training"]["interrupted"] is True


def _interrupt_at(monkeypatch, call: int):
    """Make the ``call``-th step of a DummyVecEnv raise KeyboardInterrupt (Ctrl-C in the middle of a rollout)."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    real, seen = DummyVecEnv.step_wait, [0]

    def step_wait(self):
        seen[0] += 1
        if seen[0] == call:
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(DummyVecEnv, "step_wait", step_wait)


def test_ppo_steps_count_only_the_steps_ppo_learnt_from(tmp_path, monkeypatch):
    """An interrupt in a rollout: its steps were collected, never learnt from, yet counted as PPO steps, so a run
    stopped before PPO's first update (the weights the clone's or the initial ones) was reported as a PPO model."""
    cfg = dict(TINY, train=["EX12"], steps=1024, seed=3, padding="bu", eval_freq=10_000)
    _interrupt_at(monkeypatch, 50)  # in the first rollout of 128 steps
    m = train(cfg, tmp_path / "a", progress=False, tensorboard=tmp_path / "tb")
    assert m["training"]["interrupted"] is True and m["training"]["timesteps"] == 49 and m["ppo_steps"] == 0
    _interrupt_at(monkeypatch, 300)  # in the third: two rollouts learnt from
    m = train(cfg, tmp_path / "b", progress=False, tensorboard=tmp_path / "tb")
    assert m["training"]["timesteps"] == 299 and m["ppo_steps"] == 256
    monkeypatch.undo()
    m = train({"steps": 128}, tmp_path / "b", resume=True, progress=False)  # counted on from the record
    assert m["ppo_steps"] == 384 and m["resumes"][-1]["ppo_steps_before"] == 256
    assert m["resumes"][-1]["ppo_steps_after"] == 384 and m["training"]["interrupted"] is False


def test_an_interrupt_after_ppo_writes_metrics_of_the_saved_weights(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the finished run's weights were evaluated left the new model.zip beside the old metrics.json
    (its PPO steps, its figures of other weights, no record of the run); the weights are now described, unevaluated,
    and fms train says so and exits 130."""
    import fms_dispatch.rl.train as tr
    from fms_dispatch.cli import main

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    out = tmp_path / "m"
    base = ["train", "EX12", "--allow-benchmarks", "--padding", "bu", "--n-envs", "1", "--steps", "128",
            "--out", str(out), "--no-progress", "--tensorboard", str(tmp_path / "tb")]
    assert main(base) == 0
    monkeypatch.setattr(tr, "evaluate_model", stop)
    assert main(["train", "--out", str(out), "--resume", "--steps", "128", "--no-progress"]) == 130
    printed = capsys.readouterr()
    assert "not evaluated" in printed.out and "fms: interrupted: the model is saved at" in printed.err
    m = json.loads((out / "metrics.json").read_text())
    assert m["training"]["interrupted"] is True and m["training"]["eval_makespan"] is None
    assert m["ppo_steps"] > 128 and m["resumes"][-1]["ppo_steps_after"] == m["ppo_steps"]


def test_a_model_file_is_replaced_only_by_a_complete_one(tmp_path, monkeypatch):
    """sb3 writes a model's zip in place: interrupted while it wrote best_model.zip, a run left a truncated file that
    no later run could load (exit 2, and fms solve failed though model.zip was intact)."""
    import stable_baselines3.common.base_class as bc

    real, calls = bc.save_to_zip_file, []

    def torn(save_path, *args, **kwargs):
        calls.append(str(save_path))
        if "best_model" in str(save_path):  # the first evaluation's best: half written, then Ctrl-C
            path = Path(save_path)
            (path if path.suffix == ".zip" else path.with_name(path.name + ".zip")).write_bytes(b"PK\x03\x04")
            raise KeyboardInterrupt
        return real(save_path, *args, **kwargs)

    monkeypatch.setattr(bc, "save_to_zip_file", torn)
    cfg = dict(TINY, train=["EX12"], steps=1024, seed=3, padding="bu", eval_freq=128, save_freq=10_000)
    out = tmp_path / "m"
    m = train(cfg, out, progress=False, tensorboard=tmp_path / "tb")
    assert m["training"]["interrupted"] is True and any("best_model" in c for c in calls)
    assert not (out / "best_model.zip").exists() and m["training"]["weights"] == "model.zip"
    assert [q.name for q in out.iterdir() if q.name.startswith(".")] == []  # no temporary left
    inst = builtin("EX12")
    assert validate(inst, ppo_solver(f"ppo:{out}")(inst)) == []  # the model loads and solves


def test_a_training_whose_reader_left_keeps_its_model(tmp_path):
    """`fms train ... | head`: sb3's progress bar, drawn on stdout, met the closed pipe and rich ended the process
    (exit 1, nothing said), leaving only config.json, which a new run and --resume both refused."""
    out = tmp_path / "m"
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "train", "EX12", "--allow-benchmarks",
                             "--padding", "bu", "--n-envs", "1", "--steps", "256", "--out", str(out), "--tensorboard",
                             str(tmp_path / "tb")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    proc.stdout.close()  # the reader left at once
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert (out / "model.zip").is_file() and json.loads((out / "metrics.json").read_text())["ppo_steps"] == 512


def test_resume_names_a_damaged_model_zip(tmp_path):
    out = tmp_path / "m"
    train(dict(TINY, train=["EX12"], steps=128, padding="bu"), out, progress=False, tensorboard=tmp_path / "tb")
    (out / "model.zip").write_bytes((out / "model.zip").read_bytes()[:100])  # a copy cut short
    with pytest.raises(ValueError, match=f"cannot resume: {out / 'model.zip'} is not a readable MaskablePPO model "
                                         r"\(the file .* wasn't a zip-file\)"):  # (it said "Error: the file ...")
        train({"steps": 128}, out, resume=True, progress=False)


def test_zero_steps_are_refused_with_the_reason(tmp_path):
    # --steps -5 said ">= 0 (0: the warm start or DAgger rounds only)", then --steps 0 a bare "must be positive"
    with pytest.raises(ValueError, match="--steps must be positive: 0 trains only a warm start or DAgger rounds, and "
                                         "this run has no warm-start expert"):
        train(dict(TINY, train=["EX12"], steps=0, padding="bu"), tmp_path / "m", progress=False)


def test_resume_checks_the_config_it_continues(tmp_path):
    # an edited config.json ran unchecked: eval_freq 0 evaluated at every step, unknown keys were ignored
    out = tmp_path / "m"
    train(dict(TINY, train=["EX12"], steps=128, padding="bu"), out, progress=False, tensorboard=tmp_path / "tb")
    saved = json.loads((out / "config.json").read_text())
    for key, value, needle in (("eval_freq", 0, "eval_freq must be an integer >= 1, got 0"),
                               ("bogus", 1, "unknown config key 'bogus'")):
        (out / "config.json").write_text(json.dumps(dict(saved, **{key: value})))
        with pytest.raises(ValueError, match=f"cannot resume: {out / 'config.json'}: .*{needle}"):
            train({"steps": 128}, out, resume=True, progress=False)


def test_a_diverging_ppo_run_says_so_and_leaves_no_config_without_weights(tmp_path):
    # learning_rate 1e308 ended in a traceback (float32 overflow) or torch's message about NaN logits, and left a
    # folder holding only config.json, which a new run and --resume both refused
    out = tmp_path / "m"
    with pytest.raises(ValueError, match="learning_rate must be a number > 0 and at most 3.4e\\+38"):
        train(dict(TINY, train=["EX12"], steps=128, padding="bu", ppo={"learning_rate": 1e308}), out,
              progress=False)
    with pytest.raises(ValueError, match="PPO diverged: the policy's outputs became NaN"):
        train(dict(TINY, train=["EX12"], steps=256, padding="bu", eval_freq=10_000, save_freq=10_000,
                   ppo={"learning_rate": 1e30}), out, progress=False, tensorboard=tmp_path / "tb")
    assert not (out / "config.json").exists()


def test_resume_refuses_options_it_cannot_apply(tmp_path, capsys):
    from fms_dispatch.cli import main

    assert main(["train", "EX12", "--out", str(tmp_path / "m"), "--steps", "-5"]) == 2
    assert "fms: error: --steps must be >= 0" in capsys.readouterr().err
    for extra in (["EX22"], ["--reward", "makespan"], ["--padding", "large"], ["--seed", "3"], ["--no-tools"]):
        assert main(["train", "--out", str(tmp_path / "m"), "--resume", "--steps", "64", *extra]) == 2
        err = capsys.readouterr().err
        assert "--resume continues the model in" in err and "it takes --steps and --dagger, not" in err
    assert not (tmp_path / "m").exists()


def test_resume_without_model_is_refused(tmp_path):
    with pytest.raises(ValueError, match="cannot resume: .* has no config.json and no model.zip from an earlier run$"):
        train({"steps": 10}, tmp_path / "none", resume=True, progress=False)
    (tmp_path / "half").mkdir()  # it said "no config.json and model.zip" of a folder holding its config.json
    (tmp_path / "half" / "config.json").write_text(json.dumps(dict(TINY, train=["EX12"], steps=10)))
    with pytest.raises(ValueError, match=r"cannot resume: .*half has no model.zip from an earlier run \(the latest"):
        train({"steps": 10}, tmp_path / "half", resume=True, progress=False)


def test_an_interrupted_warm_start_leaves_a_folder_a_new_run_takes(tmp_path, monkeypatch):
    """config.json was written before the warm start: Ctrl-C in it left a folder that a new run refused (it holds a
    model) and --resume too (no model.zip)."""
    from fms_dispatch.rl import imitation

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    cfg = dict(TINY, train=["EX12"], steps=0, padding="bu", warm_start={"expert": "rules", "epochs": 1})
    monkeypatch.setattr(imitation, "clone", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "m", progress=False)
    assert list((tmp_path / "m").iterdir()) == []
    monkeypatch.undo()
    assert train(cfg, tmp_path / "m", progress=False)["ppo_steps"] == 0


def test_train_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError, match="no training instances"):
        train(dict(TINY, steps=10), tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="unknown reward"):
        train(dict(TINY, train=["EX12"], reward="speed", steps=10), tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="unknown warm-start expert 'oracle'"):
        train(dict(TINY, train=["EX12"], steps=10, warm_start={"expert": "oracle"}), tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="config: n_envs must be an integer >= 1, got 0"):
        train(dict(TINY, train=["EX12"], steps=10, n_envs=0), tmp_path / "x", progress=False)
    # a misspelt key trained the default 100,000 steps; wrong kinds failed deep inside torch or sb3
    for bad, msg in [(dict(step=256), r"unknown config key 'step' \(did you mean 'steps'\?\)"),
                     (dict(ppo={"n_step": 64}), r"unknown config key 'ppo.n_step' \(did you mean 'n_steps'\?\)"),
                     (dict(hidden="big"), 'config: hidden must be an integer >= 1, got "big"'),
                     (dict(eval_freq=0), "config: eval_freq must be an integer >= 1, got 0"),
                     (dict(steps="100"), 'config: steps must be an integer >= 0, got "100"'),
                     (dict(warm_start={"lr": -1}),
                      "config: warm_start.lr must be a number > 0 and at most 3.4e\\+38, got -1"),
                     (dict(fleet=[1]), "config key fleet must be an object"),
                     (dict(net_arch=[64, 0]), "config: net_arch must be a list of layer widths"),
                     (dict(seed=-1), "config: seed must be an integer from 0 to 2147483647, got -1")]:  # gym's error
        with pytest.raises(ValueError, match=msg):
            train(dict(TINY, train=["gen:6x4x3*1@5"], **bad), tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="cannot read the shop specs") as info:  # a typo, not a benchmark
        train(dict(TINY, train=["gen:6x4x3*1@5", "gne:6x4"], steps=10, allow_benchmarks=False), tmp_path / "x",
              progress=False)
    assert "--allow-benchmarks" not in str(info.value)
    with pytest.raises(ValueError, match="init: no weights at models/nosuchmodel"):
        train(dict(TINY, train=["EX12"], steps=10, init="models/nosuchmodel"), tmp_path / "x", progress=False)
    # a shop larger than the padding is refused before the workers start (in a worker: a traceback, a broken pipe)
    with pytest.raises(ValueError, match=r"shop gen5x4s1_00 has 4 tools, more than the model's padded maximum 0 "
                                         r"\(padding bu; --padding auto fits every shop\)"):
        train(dict(TINY, train=["gen:5x4x4*2@1"], steps=64, padding="bu", n_envs=2, vec_env="subproc"),
              tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()  # refused before anything was written
    (tmp_path / "f").write_text("")
    with pytest.raises(ValueError, match="is a file"):
        train(dict(TINY, train=["EX12"], steps=10), tmp_path / "f", progress=False)


def test_fms_train_refuses_a_config_that_is_no_object_and_empty_names(tmp_path, capsys, monkeypatch):
    from fms_dispatch.cli import main

    monkeypatch.chdir(tmp_path)  # (where --out '' would have trained)

    for text in ("[]", '[["steps", 5]]', "5", "null"):  # [] trained 100,000 default steps, 5 was a traceback
        (tmp_path / "c.json").write_text(text)
        code = main(["train", "gen:5x4x2*2@1", "--config", str(tmp_path / "c.json"), "--out", str(tmp_path / "m")])
        err = capsys.readouterr().err
        assert code == 2 and "must hold a JSON object of hyper-parameters" in err, (text, err)
    (tmp_path / "afile").write_text("x")
    for extra, msg in ((["--out", ""], "--out names nothing"), (["--out", str(tmp_path / "m"), "--tensorboard", ""],
                                                                 "--tensorboard names nothing"),
                       (["--out", str(tmp_path / "m"), "--tensorboard", str(tmp_path / "afile")], "is a file")):
        code = main(["train", "gen:5x4x2*2@1", *extra])
        err = capsys.readouterr().err
        assert code == 2 and msg in err, (extra, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "c.json"]  # nothing trained, no folder made


def test_init_names_a_shipped_model_from_any_folder(tmp_path, monkeypatch):
    """A shipped config's ``init: models/guided`` (and the bare name) finds the shipped model when training runs
    from another working folder, not only from the repository's root."""
    from fms_dispatch.rl.models import resolve_model
    from fms_dispatch.rl.train import _resolve_init

    monkeypatch.chdir(tmp_path)
    shipped = resolve_model("guided").folder
    assert _resolve_init("models/guided") == shipped and _resolve_init("guided") == shipped
    (tmp_path / "models" / "guided").mkdir(parents=True)  # a folder of that name here is what is meant
    assert (tmp_path / _resolve_init("models/guided")).resolve() == (tmp_path / "models" / "guided").resolve()


def _best_rule_makespan(inst, include_nearest):
    from fms_dispatch.rules import all_rule_pairs, parse_rule_name
    from fms_sim.shop import run_policy

    return min(run_policy(inst, parse_rule_name(name)).makespan for name in all_rule_pairs(include_nearest))


def test_training_on_benchmark_or_held_out_shops_is_refused_unless_allowed(tmp_path):
    base = {k: v for k, v in TINY.items() if k != "allow_benchmarks"}
    for cfg, culprit in ((dict(base, train=["EX12"], steps=10), "EX12"),
                         (dict(base, train=["gen:6x4x3*1@5"], eval=["sl00"], steps=10), "sl00"),
                         (dict(base, train=["ho03"], steps=10), "ho03")):
        with pytest.raises(ValueError, match=f"(?s)generated shops only.*{culprit}.*--allow-benchmarks"):
            train(cfg, tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()
    m = train(dict(base, train=["EX12"], steps=0, allow_benchmarks=True, padding="bu",
                   warm_start={"expert": "rules", "epochs": 1}), tmp_path / "ok", progress=False)
    assert json.loads((tmp_path / "ok" / "config.json").read_text())["allow_benchmarks"] is True
    # nor from a model that trained on them (a fine-tuned model was recorded as trained apart: its config's own
    # specs were all that was checked), whether its config says so or only its recorded shops
    fine = dict(base, train=["genbu:1*1@1"], steps=10, padding="bu", init=str(tmp_path / "ok"))
    with pytest.raises(ValueError, match=r"init .*ok: a model trained on benchmark instances or held-out shops "
                                         r"\(its training shops include EX12\); a model fine-tuned from it"):
        train(fine, tmp_path / "ft", progress=False)
    card = tmp_path / "ok" / "metrics.json"
    card.write_text(json.dumps(dict(json.loads(card.read_text()), training_shops=[])))
    with pytest.raises(ValueError, match=r"\(its config sets allow_benchmarks\)"):
        train(fine, tmp_path / "ft", progress=False)
    assert not (tmp_path / "ft").exists()
    assert m["training"]["eval_makespan"]["EX12"] > 0
    # no PPO step, no evaluation: the best reward is null, and the metrics are strict JSON (no -Infinity)
    strict = json.loads((tmp_path / "ok" / "metrics.json").read_text(),
                        parse_constant=lambda c: pytest.fail(f"{c} in metrics.json"))
    assert strict["training"]["best_mean_reward"] is None or abs(strict["training"]["best_mean_reward"]) < 1e9


def test_shipped_models_train_apart():
    """No shipped model trains or selects on a benchmark instance or a held-out shop (issue 19)."""
    from pathlib import Path

    from fms_sim.shopsets import check_training_specs, expand_specs

    from fms_dispatch.rl.models import SHIPPED

    root = Path(__file__).resolve().parents[2] / "models"
    # the shipped ones (a folder of the user's own, `fms train --out models/mine`, failed the suite)
    folders = [root / name for name in SHIPPED]
    assert all((p / "config.json").is_file() for p in folders)
    for folder in folders:
        cfg = json.loads((folder / "config.json").read_text())
        assert not cfg.get("allow_benchmarks"), folder.name
        check_training_specs(cfg)
        # each model card lists its training shops, its PPO steps and its held-out results
        metrics = json.loads((folder / "metrics.json").read_text())
        specs = cfg["train"] + [x for st in cfg["warm_start"].get("refine", []) for x in st["train"]]
        own = [i.name for i in expand_specs(specs, cfg["fleet"])]
        if cfg.get("init"):  # a fine-tuned model has seen its initial model's shops too
            own += json.loads((root.parent / cfg["init"] / "metrics.json").read_text())["training_shops"]
        assert metrics["training_shops"] == list(dict.fromkeys(own))
        assert metrics["ppo_steps"] == metrics["training"]["timesteps"]
        held = metrics["heldout"]["shops"]
        assert held and all(name.startswith("ho") and "ppo" in row for name, row in held.items())


def test_bench_training_configs_train_apart():
    """The training configs of the benches' experiments (bench/configs) train and select on generated shops only,
    and start from a shipped model that exists."""
    from pathlib import Path

    from fms_sim.shopsets import check_training_specs

    root = Path(__file__).resolve().parents[2]
    configs = sorted((root / "bench" / "configs").glob("*.json"))
    assert configs
    for path in configs:
        cfg = json.loads(path.read_text())
        assert not cfg.get("allow_benchmarks"), path.name
        check_training_specs(cfg)
        if cfg.get("init"):
            assert (root / cfg["init"] / "best_model.zip").is_file(), path.name


@pytest.mark.parametrize("expert,nearest", [("rules", False), ("rules+nearest", True)])
def test_rule_experts_replay_the_best_pair(expert, nearest):
    """The rule experts' demonstrations replay, through the env, the best pair of their set (24 or 36)."""
    from fms_dispatch.rl.imitation import demonstrations, rule_trajectory

    inst = expand_instances(["gen:6x4x3*1@5"])[0]
    ms, seq = rule_trajectory(inst, include_nearest=nearest)
    assert ms == _best_rule_makespan(inst, nearest)
    pad = padding_for("auto", [inst])
    demos, makespans = demonstrations([inst], pad, "shaped", expert)
    assert makespans == {inst.name: ms}
    n = len(demos["action"])
    assert 0 < n <= len(seq) and demos["obs"].shape[0] == demos["mask"].shape[0] == demos["ret"].shape[0] == n
    assert demos["mask"][np.arange(n), demos["action"]].all()  # every recorded action was legal
    assert (demos["mask"].sum(axis=1) > 1).all()  # forced moves are not recorded
    with pytest.raises(ValueError, match="unknown expert 'oracle'"):
        demonstrations([inst], pad, "shaped", "oracle")


def test_nearest_expert_sees_pairs_the_paper_set_does_not():
    """On the large benchmark's layout the 36-pair expert is at least as good as the 24-pair one on every
    instance and strictly better on some (the reason the large models are cloned from it)."""
    from fms_dispatch.rl.imitation import rule_trajectory

    insts = expand_instances(["gen:8x5x5*4@3"])
    pairs = [(rule_trajectory(i)[0], rule_trajectory(i, include_nearest=True)[0]) for i in insts]
    assert all(b <= a for a, b in pairs) and any(b < a for a, b in pairs), pairs


def test_sequence_policy_replays_its_sequence_and_falls_back_deterministically():
    """A sequence policy replays a run exactly; where its entry is illegal it takes a hashed legal action,
    the same on every run (so the lookahead's twins make the run's own choices)."""
    from fms_dispatch.rl.imitation import SequencePolicy, rule_trajectory
    from fms_sim.shop import run_policy

    inst = builtin("EX22")
    ms, seq = rule_trajectory(inst)
    assert run_policy(inst, SequencePolicy(seq)).makespan == ms
    holes = [a if t % 3 else -1 for t, a in enumerate(seq)]
    runs = [run_policy(inst, SequencePolicy(holes, salt=s)) for s in (5, 5, 6)]
    assert all(validate(inst, r) == [] for r in runs)
    assert runs[0].to_dict() == runs[1].to_dict()


def test_lookahead_search_judges_sequences_by_their_lookahead_runs():
    """The lookahead search returns a policy whose lookahead run has the makespan it reports, valid, no worse
    than the lookahead run of its start; its demonstration reproduces that run and labels legal actions."""
    from fms_dispatch.rl.imitation import (SequencePolicy, lookahead_demonstration, lookahead_search,
                                           search_trajectory)
    from fms_dispatch.rl.lookahead import run_with_lookahead
    from fms_sim.shop import Shop

    inst = builtin("EX22")
    _, start = search_trajectory(inst, iters=100, seed=3)
    start_ms = run_with_lookahead(Shop(inst), SequencePolicy(start)).makespan
    ms, policy = lookahead_search(inst, iters=150, seed=3, start=start)
    assert ms <= start_ms
    decisions: list = []
    sched = run_with_lookahead(Shop(inst), policy, decisions=decisions)
    assert sched.makespan == ms and validate(inst, sched) == []
    assert all(a in legal for legal, a in decisions)
    pad = padding_for("bu", [inst])
    demo_ms, demos, conflicts = lookahead_demonstration(inst, policy, pad)
    assert demo_ms == ms and conflicts == 0
    n = len(demos["action"])
    assert n >= sum(len(legal) > 1 for legal, _ in decisions) > 0  # the twins' decisions come on top
    assert demos["mask"][np.arange(n), demos["action"]].all() and np.isnan(demos["ret"]).all()


def test_insertion_move_moves_a_later_decision_forward():
    """The insertion move takes the first later occurrence out and puts it in front; nothing to move when
    the action does not come later (the search then overwrites instead)."""
    from fms_dispatch.rl.imitation import _inserted

    assert _inserted([5, 1, 2, 3, 2], 1, 2) == [5, 2, 1, 3, 2]
    assert _inserted([5, 1, 2, 3], 0, 3) == [3, 5, 1, 2]
    assert _inserted([5, 1, 2, 3], 2, 1) is None and _inserted([5, 1, 2, 3], 3, 3) is None


def test_lookahead_search_with_insertions_and_restarts_keeps_its_guarantees():
    """With insertion moves and restarts the search still returns a reproducible policy whose valid lookahead
    run has the reported makespan; a second restart only adds to the first (same random stream), so it is
    never worse than one restart."""
    from fms_dispatch.rl.imitation import lookahead_search, search_trajectory
    from fms_dispatch.rl.lookahead import run_with_lookahead
    from fms_sim.shop import Shop

    inst = builtin("EX42")
    _, start = search_trajectory(inst, iters=100, seed=4)
    one_ms, _ = lookahead_search(inst, iters=60, seed=4, start=start, insert=0.5)
    two_ms, policy = lookahead_search(inst, iters=60, seed=4, start=start, insert=0.5, restarts=2)
    assert two_ms <= one_ms
    sched = run_with_lookahead(Shop(inst), policy)
    assert sched.makespan == two_ms and validate(inst, sched) == []
    again_ms, again = lookahead_search(inst, iters=60, seed=4, start=start, insert=0.5, restarts=2)
    assert again_ms == two_ms and again.actions == policy.actions and again.salt == policy.salt


def test_search_lookahead_demonstrations_keep_the_best_start_whatever_the_worker_count():
    """Several independent starts per instance keep the best (never worse than the first start alone, which
    is the single-start search); workers=2 runs the searches in separate processes and gives the same arrays
    and makespans, in instance order, as one process."""
    from fms_dispatch.rl.imitation import demonstrations

    insts = expand_instances(["gen:6x4x3*2@7"])
    pad = padding_for("auto", insts)
    kw = dict(iters=10, seed=2, insert=0.5, restarts=1)  # short searches, so that later starts find better ones
    _, single_ms = demonstrations(insts, pad, "shaped", "search+lookahead", **kw)
    one, one_ms = demonstrations(insts, pad, "shaped", "search+lookahead", starts=3, workers=1, **kw)
    lines: list[str] = []
    two, two_ms = demonstrations(insts, pad, "shaped", "search+lookahead", starts=3, workers=2,
                                 progress=lines.append, **kw)
    assert all(one_ms[k] <= single_ms[k] for k in single_ms)
    assert all(one_ms[k] < single_ms[k] for k in single_ms)  # here a later start wins on both: it is the one kept
    assert one_ms == two_ms and list(two_ms) == [i.name for i in insts]
    assert set(one) == set(two) and all(np.array_equal(one[k], two[k], equal_nan=True) for k in one)
    assert len(lines) == 2 and lines[-1].startswith("  demonstrations: 2/2 instances") and "starts: " in lines[-1]


def test_search_lookahead_expert_clones_into_a_policy_that_repeats_its_lookahead_run(tmp_path):
    """Warm start from the search+lookahead expert: once every recorded decision is matched, solving with the
    model and the lookahead reproduces the expert's makespan (the point of recording the twins' decisions)."""
    out = tmp_path / "la"
    cfg = dict(TINY, train=["gen:6x4x3*1@5"], eval=["gen:6x4x3*1@5"], steps=0, seed=2, padding="auto",
               arch="mlp", net_arch=[64, 64], warm_start={"expert": "search+lookahead", "instances": 1,
                                                          "search_iters": 60, "epochs": 300, "lr": 3e-3})
    m = train(cfg, out, tensorboard=tmp_path / "tb")
    w = m["warm_start"]
    assert w["accuracy"] == 1.0 and w["samples"] > 0
    inst = expand_instances(["gen:6x4x3*1@5"])[0]
    s = ppo_solver(f"ppo:{out}")(inst, lookahead=True)
    assert validate(inst, s) == [] and s.makespan == w["expert_makespan"][inst.name]


def test_warm_start_only_training_clones_the_expert(tmp_path, capsys):
    """steps=0 with an expert: the model is the cloned policy; metrics record the cloning figures; the
    demonstrations and the cloning report progress."""
    out = tmp_path / "clone"
    cfg = dict(TINY, train=["gen:6x4x3*2@5"], eval=["gen:6x4x3*1@9"], steps=0, seed=1, padding="auto",
               warm_start={"expert": "rules+nearest", "instances": 2, "epochs": 30})
    m = train(cfg, out, progress=True, tensorboard=tmp_path / "tb")
    printed = capsys.readouterr().err  # progress goes to stderr
    assert "demonstrations: 2/2 instances" in printed and "cloning: epoch 30/30" in printed
    w = m["warm_start"]
    assert w["expert"] == "rules+nearest" and w["samples"] > 0 and 0.0 <= w["accuracy"] <= 1.0
    assert set(w["expert_makespan"]) == {i.name for i in expand_instances(["gen:6x4x3*2@5"])}
    assert m["training"]["timesteps"] == 0 and (out / "best_model.zip").is_file()
    inst = expand_instances(["gen:6x4x3*1@9"])[0]
    s = ppo_solver(f"ppo:{out}")(inst)
    assert validate(inst, s) == [] and s.makespan == m["training"]["eval_makespan"][inst.name]


def test_pair_demonstrations_replay_one_pair_on_every_instance():
    """pair_demonstrations labels every instance with the same pair (not each instance's best)."""
    from fms_dispatch.rl.imitation import pair_demonstrations
    from fms_dispatch.rules import parse_rule_name
    from fms_sim.shop import run_policy

    insts = expand_instances(["gen:6x4x3*2@5"])
    pad = padding_for("auto", insts)
    demos, makespans = pair_demonstrations(insts, "MTWR+nearest", pad, "shaped")
    assert makespans == {i.name: run_policy(i, parse_rule_name("MTWR+nearest")).makespan for i in insts}
    n = len(demos["action"])
    assert n > 0 and demos["obs"].shape[0] == demos["ret"].shape[0] == n
    assert demos["mask"][np.arange(n), demos["action"]].all() and (demos["mask"].sum(axis=1) > 1).all()
    other, _ = pair_demonstrations(insts, "LPT+first", pad, "shaped")
    assert not (len(other["action"]) == n and (other["action"] == demos["action"]).all())  # the pair matters
    with pytest.raises(ValueError, match="unknown job rule"):
        pair_demonstrations(insts, "BEST+nearest", pad, "shaped")


def test_refine_stage_clones_one_pair_after_the_warm_start(tmp_path):
    """warm_start.refine: after cloning the expert, each stage clones one pair on its instances; the figures
    are recorded and the weights differ from the run without the stage; bad stages are refused up front."""
    from sb3_contrib import MaskablePPO

    base = dict(TINY, train=["gen:6x4x3*2@5"], eval=["gen:6x4x3*1@9"], steps=0, seed=1, padding="auto")
    # the stage's instances are larger than the expert's: the automatic padding must cover them
    stage = {"train": ["gen:7x5x3*2@7"], "pair": "MTWR+nearest", "epochs": 3, "lr": 1e-3}
    plain = train(dict(base, warm_start={"expert": "rules+nearest", "instances": 2, "epochs": 3}),
                  tmp_path / "plain", progress=False)
    m = train(dict(base, warm_start={"expert": "rules+nearest", "instances": 2, "epochs": 3, "refine": [stage]}),
              tmp_path / "refined", progress=False)
    assert not plain["warm_start"]["refine"]
    (fig,) = m["warm_start"]["refine"]
    assert fig["pair"] == "MTWR+nearest" and fig["instances"] == 2 and fig["epochs"] == 3 and fig["samples"] > 0
    assert fig["seed"] == 2  # seed + 1 + k by default
    assert json.loads((tmp_path / "refined" / "config.json").read_text())["warm_start"]["refine"] == [stage]
    w0 = MaskablePPO.load(str(tmp_path / "plain" / "best_model.zip"), device="cpu").policy.state_dict()
    w1 = MaskablePPO.load(str(tmp_path / "refined" / "best_model.zip"), device="cpu").policy.state_dict()
    assert any(not np.array_equal(w0[k].numpy(), w1[k].numpy()) for k in w0)
    inst = expand_instances(["gen:6x4x3*1@9"])[0]
    assert validate(inst, ppo_solver(f"ppo:{tmp_path / 'refined'}")(inst)) == []
    for bad, why in (([dict(stage, pair="BEST+nearest")], "unknown job rule"),
                     ([{"pair": "MTWR+nearest"}], r"refine\[0\] needs train"),
                     ([dict(stage, epochs=0)], "epochs must be"),
                     # int() and float() took these (2, 1, a NaN or infinite rate), a string train its letters
                     ([dict(stage, epochs=2.9)], "epochs must be an integer >= 1, got 2.9"),
                     ([dict(stage, epochs=True)], "epochs must be an integer >= 1, got True"),
                     ([dict(stage, lr="nan")], "lr must be a positive, finite number, got 'nan'"),
                     ([dict(stage, lr=float("inf"))], "lr must be a positive, finite number, got inf"),
                     ([dict(stage, seed=-3)], "seed must be an integer from 0"),
                     ([dict(stage, train="gen:7x5x3*2@7")], "train must be a list of instance specs"),
                     ({"train": ["EX12"]}, "must be a list")):
        with pytest.raises(ValueError, match=why):
            train(dict(base, warm_start={"expert": "rules+nearest", "refine": bad}), tmp_path / "bad",
                  progress=False)
    with pytest.raises(ValueError, match="set warm_start.expert"):
        train(dict(base, steps=10, warm_start={"refine": [stage]}), tmp_path / "bad", progress=False)
    assert not (tmp_path / "bad").exists()


def test_dagger_labels_the_policys_own_states_with_the_expert_pair(tmp_path):
    """A DAgger round runs the policy itself (its makespans are those of solving with the saved model) and
    labels each state it visits with the legal action of the instance's expert pair."""
    from sb3_contrib import MaskablePPO

    from fms_dispatch.rl.imitation import dagger_round, demonstrations
    from fms_dispatch.rules import parse_rule_name

    out = tmp_path / "m"
    insts = expand_instances(["gen:6x4x3*2@5"])
    train(dict(TINY, train=["gen:6x4x3*2@5"], eval=["gen:6x4x3*2@5"], steps=0, seed=1, padding="auto",
               warm_start={"expert": "rules+nearest", "instances": 2, "epochs": 2}), out, progress=False)
    model = MaskablePPO.load(str(out / "best_model.zip"), device="cpu")
    pad = padding_for("auto", insts)
    pairs: dict[str, str] = {}
    demonstrations(insts, pad, "shaped", "rules+nearest", pairs=pairs)
    assert set(pairs) == {i.name for i in insts}
    labelled, policy_ms = dagger_round(model, insts, pairs, pad, "shaped")
    for inst in insts:
        s = ppo_solver(f"ppo:{out}")(inst)
        assert policy_ms[inst.name] == s.makespan
    n = len(labelled["action"])
    assert n > 0 and labelled["obs"].shape[0] == labelled["ret"].shape[0] == n
    assert labelled["mask"][np.arange(n), labelled["action"]].all()
    # the first state is the same for policy and expert: its label is the expert pair's first choice
    from fms_sim.shop import Shop

    first = insts[0]
    expert_first = parse_rule_name(pairs[first.name])(Shop(first))
    assert labelled["action"][0] == _padded(first, pad, expert_first)
    with pytest.raises(ValueError, match="no expert rule pair"):
        dagger_round(model, insts, {}, pad, "shaped")


def _padded(inst, pad, net_action):
    from fms_dispatch.rl.envs import FastShopEnv

    env = FastShopEnv(inst, **pad)
    env.reset(options={"instance": inst})
    return env.from_net_action(net_action)


def test_dagger_rounds_in_training_and_on_resume(tmp_path, capsys):
    """warm_start.dagger rounds follow the cloning; ``--resume --dagger N`` adds rounds to a saved model and
    counts them in its config and metrics; bad requests are refused."""
    out = tmp_path / "dg"
    cfg = dict(TINY, train=["gen:6x4x3*2@5"], eval=["gen:6x4x3*1@9"], steps=0, seed=1, padding="auto",
               warm_start={"expert": "rules+nearest", "instances": 2, "epochs": 3, "dagger": 1,
                           "dagger_epochs": 2})
    m = train(cfg, out, progress=True, tensorboard=tmp_path / "tb")
    printed = capsys.readouterr().err  # progress goes to stderr
    assert "dagger round 1/1" in printed and "dagger: 2/2 instances" in printed
    rounds = m["warm_start"]["dagger_rounds"]
    assert [r["round"] for r in rounds] == [1] and rounds[0]["policy_vs_expert"] > 0
    assert rounds[0]["samples"] > m["warm_start"]["samples"]  # the policy's states were added
    m2 = train({"steps": 0}, out, resume=True, progress=False, dagger=1)
    assert len(m2["warm_start"]["dagger_rounds"]) == 2 and m2["warm_start"]["dagger"] == 2
    assert [r["round"] for r in m2["warm_start"]["dagger_rounds"]] == [1, 2]  # (the added one was round 1 again)
    assert json.loads((out / "config.json").read_text())["warm_start"]["dagger"] == 2
    inst = expand_instances(["gen:6x4x3*1@9"])[0]
    assert validate(inst, ppo_solver(f"ppo:{out}")(inst)) == []
    with pytest.raises(ValueError, match="--dagger N adds rounds"):
        train(dict(cfg, warm_start={"expert": "rules"}), tmp_path / "y", progress=False, dagger=1)
    with pytest.raises(ValueError, match="--dagger must be >= 0 .DAgger rounds to add., got -1"):  # of a resumed
        train({"steps": 0}, out, resume=True, progress=False, dagger=-1)  # model: "adds rounds to a model resumed"
    with pytest.raises(ValueError, match="DAgger needs a rule-pair or plan warm-start expert"):
        train(dict(cfg, warm_start={"expert": "search", "dagger": 1}), tmp_path / "y", progress=False)
    assert not (tmp_path / "y").exists()


def test_train_cli_parser():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd")
    add_train_parser(sub)
    a = p.parse_args(["train", "EX12", "EX22", "--steps", "100", "--reward", "idle", "--seed", "3", "--out", "m/x"])
    assert a.instances == ["EX12", "EX22"] and a.steps == 100 and a.reward == "idle" and a.out == "m/x"
    with pytest.raises(SystemExit):
        p.parse_args(["train", "EX12", "--reward", "speed", "--out", "m"])
    a = p.parse_args(["train", "--out", "m/x"])
    with pytest.raises(ValueError, match="training instances"):
        a.fn(a)


def test_solver_spec_errors():
    with pytest.raises(ValueError, match="ppo:MODEL"):
        ppo_solver("ppo:")
    with pytest.raises(ValueError, match="ppo:MODEL"):
        ppo_solver("dqn")
    with pytest.raises(ValueError, match="no model named"):
        ppo_solver("ppo:no-such-model")(builtin("EX12"))


def test_default_model_choice():
    assert default_model_name(builtin("EX12")) == "guided-dagger"  # chosen on BU-size validation shops over bu
    assert default_model_name(builtin("ra01")) == "guided-dagger"  # tools: the guided full-net model
    assert default_model_name(builtin("sl00")) == "guided-dagger"
    assert default_model_name(builtin("sl00").without_tools()) == "guided-dagger"
    import dataclasses

    assert default_model_name(dataclasses.replace(builtin("EX12"), n_agvs=3)) == "guided-dagger"  # more AGVs


# ---------------------------------------------------------------------- shipped models
def test_shipped_models_exist_and_are_small():
    for name in SHIPPED:
        ref = resolve_model(name)
        assert ref.folder == models_dir() / name
        for f in ref.folder.iterdir():
            assert f.stat().st_size <= 10 * 2**20, f
        assert (ref.folder / "config.json").is_file() and (ref.folder / "metrics.json").is_file()


def test_shipped_models_have_current_numpy_exports():
    """Every shipped weights file has its actor export, and the export is of exactly those weights (a
    retrained model without a new export would silently fall back to torch)."""
    from fms_dispatch.rl.actors import actor_path, file_sha256, load_actor

    for name in SHIPPED:
        ref = resolve_model(name)
        for weights in ref.folder.glob("*.zip"):
            actor, sha = load_actor(actor_path(weights))
            assert sha == file_sha256(weights), weights


@pytest.mark.parametrize("name", SHIPPED)
def test_the_batched_small_blocks_give_the_block_by_block_logits(name):
    """The numpy actor embeds the machines, tools, AGVs and transporters in one batched pass; on every shipped
    model it gives the logits of embedding them block by block, on shops with and without tools and AGVs (blocks
    with no rows), with fewer rows than the padding (ra01: 10 machines of 20) and at the padding (EX12 and EX104,
    bu)."""
    import copy

    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import load_agent
    from fms_sim.formats import load_instance
    from fms_sim.full_shop import make_shop

    agent = load_agent(name)
    assert agent.actor._small is not None  # every shipped model is an entity network of two-layer blocks
    plain = copy.copy(agent.actor)
    plain._small = None
    if agent.guide is not None:
        agent.use_guide_effort(effort_from(restarts=0, tabu=0))
    if name == "bu":
        shops = [load_instance("EX12"), load_instance("EX104")]
    else:
        shops = [load_instance("ra01"), load_instance("ra01", no_tools=True), builtin("ta01")]
    compared = 0
    for inst in shops:
        if not agent.fits(inst):
            continue
        shop = make_shop(inst, agent.decisions)
        for _ in range(200 if name == "bu" else 60):
            if shop.done:
                break
            if len(shop.legal_actions()) > 1:
                obs, mask = agent._env(shop).observe()
                got, want = agent.actor.logits(obs, mask), plain.logits(obs, mask)
                assert np.array_equal(np.isfinite(got), np.isfinite(want))
                assert np.allclose(got[mask], want[mask], rtol=0, atol=1e-4)
                compared += 1
            shop.act(agent.act(shop))
    assert compared >= 20


def test_the_numpy_actor_scores_a_head_alone_as_with_every_action_legal():
    """Each head of the numpy actor is scored only where its action block has a legal action, its context part in
    one product with the other needed heads': a single legal action gets, to the last bit, the logit it gets with
    every action legal, every other action is -inf, and a mask without a legal action gives all -inf."""
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import load_agent
    from fms_sim.full_shop import make_shop

    inst = builtin("sl00")
    agent = load_agent(default_model_name(inst))
    if agent.guide is not None:
        agent.use_guide_effort(effort_from(restarts=0, tabu=0))
    actor = agent.actor
    shop = make_shop(inst, agent.decisions)
    for _ in range(30):
        shop.act(agent.act(shop))
    obs, mask = agent._env(shop).observe()
    everything = actor.logits(obs, np.ones_like(mask))
    assert np.all(np.isneginf(actor.logits(obs, np.zeros_like(mask))))
    checked = set()
    for head in actor.heads:
        if head == "hold":
            slots = [actor._hold]
        else:
            lo, _, block = actor._where[head]
            i, f = actor._parts[block][0]
            slots = lo + np.flatnonzero(obs[i:i + actor.lay[block] * f:f])  # the rows that exist
        for slot in slots[:2]:
            one = np.zeros_like(mask)
            one[slot] = True
            got = actor.logits(obs, one)
            assert np.isfinite(got[slot]) and np.sum(np.isfinite(got)) == 1
            assert got[slot] == everything[slot]
            checked.add(head)
    assert checked == set(actor.heads)  # every head, on sl00 (15 jobs, tools, AGVs and transporters)


def test_solving_with_a_shipped_model_does_not_import_torch():
    code = ("import sys; from fms_dispatch.rl import ppo_solver; from fms_sim.benchmarks import builtin; "
            "s = ppo_solver('ppo')(builtin('EX12'), lookahead=True); "
            "print(s.makespan, s.meta['model'], 'torch' in sys.modules, 'sb3_contrib' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    makespan, model, torch_loaded, sb3_loaded = res.stdout.split()
    assert model == "guided-dagger" and torch_loaded == "False" and sb3_loaded == "False"
    assert int(makespan) == ppo_solver("ppo")(builtin("EX12"), lookahead=True).makespan


def test_stale_or_broken_export_falls_back_to_torch(tmp_path):
    import shutil

    from fms_dispatch.rl.actors import actor_path
    from fms_dispatch.rl.agent import Agent

    ref = resolve_model("bu")
    weights = tmp_path / "best_model.zip"
    shutil.copy(ref.weights, weights)
    shutil.copy(ref.folder / "config.json", tmp_path / "config.json")
    shutil.copy(resolve_model("large").weights.with_name("best_model.actor.npz"), actor_path(weights))  # stale
    agent = Agent(weights, ref.padding)
    assert agent.uses_torch
    actor_path(weights).write_bytes(b"not an npz")
    assert Agent(weights, ref.padding).uses_torch
    good = ref.weights.with_name("best_model.actor.npz").read_bytes()
    for broken in (b"", good[:1000], good[:-200]):  # empty, truncated (an interrupted copy or a full disk)
        actor_path(weights).write_bytes(broken)
        assert Agent(weights, ref.padding).uses_torch
    import json

    import numpy as np

    with np.load(ref.weights.with_name("best_model.actor.npz")) as data:
        arrays = dict(data)
    meta = json.loads(bytes(arrays["meta"]).decode())
    for bad in ([meta], {k: v for k, v in meta.items() if k != "source_sha256"}):  # an AttributeError, a KeyError
        np.savez(actor_path(weights), **dict(arrays, meta=np.frombuffer(json.dumps(bad).encode(), dtype=np.uint8)))
        assert Agent(weights, ref.padding).uses_torch
    shutil.copy(ref.weights.with_name("best_model.actor.npz"), actor_path(weights))  # the right export
    fast = Agent(weights, ref.padding)
    assert not fast.uses_torch
    inst = builtin("EX32")
    assert (ppo_solver(f"ppo:{weights}")(inst).makespan
            == ppo_solver("ppo:bu")(inst).makespan)


def test_shipped_bu_model_valid_on_ex12():
    inst = builtin("EX12")
    s = ppo_solver("ppo:bu")(inst)
    assert s.meta["model"] == "bu" and s.meta["decisions"] == "paper"
    assert validate(inst, s) == []


@pytest.mark.parametrize("name,no_tools", [("large", False), ("large-agv", True), ("guided", False), ("guided", True)])
def test_shipped_large_models_valid_on_sl00(name, no_tools):
    inst = builtin("sl00")
    if no_tools:
        inst = inst.without_tools()
    solve = ppo_solver(f"ppo:{name}")
    t0 = time.perf_counter()
    s = solve(inst)
    assert time.perf_counter() - t0 < 10.0
    assert s.meta["model"] == name
    assert validate(inst, s) == []


def test_bu_model_refuses_too_large_instance():
    """The error names what exceeds the model's padding (sl00: 15 jobs, 15 machines, 15 tools, 10 AGVs, 5
    transporters against bu's 8 / 4 / 0 / 2 / 0) and the solvers that take any size."""
    with pytest.raises(ValueError) as err:
        ppo_solver("ppo:bu")(builtin("sl00"))
    msg = str(err.value)
    assert msg.startswith("instance sl00 is larger than model bu allows: 15 jobs (at most 8), 15 machines (at most "
                          "4), 15 tools (at most 0), 10 AGVs (at most 2), 5 tool transporters (at most 0); ")
    assert "rule:MTWR+nearest" in msg and "plan:list" in msg
    with pytest.raises(ValueError, match=r"larger than model bu allows: 10 AGVs \(at most 2\); a rule"):
        ppo_solver("ppo:bu")(builtin("EX12").with_fleet(n_agvs=10))
    with pytest.raises(ValueError, match=r"allows: 4 tools \(at most 0\), 1 tool transporter \(at most 0\); "):
        ppo_solver("ppo:bu")(builtin("ra01").with_fleet(n_tool_transporters=1))  # (it said "1 tool transporters")


def test_models_record_the_net_they_were_trained_on_and_load_with_it(tmp_path):
    import json
    import shutil

    from fms_dispatch.rl.models import load_agent, resolve_model
    from fms_dispatch.rl.train import DEFAULT_CONFIG

    assert DEFAULT_CONFIG["decisions"] == "paper"
    for name in ("bu", "large", "large-agv"):
        ref = resolve_model(name)
        assert ref.config["decisions"] == "paper" == ref.decisions
    assert load_agent("bu").decisions == "paper"
    s = ppo_solver("ppo:bu")(builtin("EX12"))
    assert s.meta["decisions"] == "paper" and validate(builtin("EX12"), s) == []
    # a model made for another net is refused by name, never run on the wrong one
    folder = tmp_path / "fullnet"
    shutil.copytree(resolve_model("bu").folder, folder)
    cfg = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**cfg, "decisions": "full"}))
    with pytest.raises(ValueError, match="model bu was trained on the 'paper' net, but its config says 'full'"):
        load_agent(str(folder))
    (folder / "config.json").write_text(json.dumps({**cfg, "decisions": "fifo"}))
    with pytest.raises(ValueError, match="unknown decisions"):
        load_agent(str(folder))


def test_guided_ppo_is_a_ppo_model_of_guided_that_solves_nominal_and_disrupted_shops():
    """guided-ppo: PPO steps from guided's weights (its card says so); its schedules pass the validator, in a
    nominal shop and in a disrupted one (checked against the scenario)."""
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import load_config
    from fms_sim.disruptions import Scenario

    ref = resolve_model("guided-ppo")
    cfg = load_config(ref.folder)
    metrics = json.loads((ref.folder / "metrics.json").read_text())
    assert cfg["init"] == "models/guided" and cfg["baseline"] == "init" and cfg["disruptions"]
    assert metrics["ppo_steps"] > 0 and metrics["warm_start"]["init"] == "models/guided"
    inst = builtin("EX42")
    solve = ppo_solver("ppo:guided-ppo")
    plain = solve(inst, guide_effort=effort_from(tabu=0.0))
    assert plain.meta["model"] == "guided-ppo" and validate(inst, plain) == []
    sc = Scenario.draw(inst, noise=0.2, breakdowns=1, horizon=40, seed=3)
    disrupted = solve(inst, scenario=sc, guide_effort=effort_from(tabu=0.0))
    assert validate(inst, disrupted, sc) == []


def test_guided_dagger_acts_as_its_expert_in_a_disrupted_shop_where_guided_does_not():
    """guided-dagger (the default): two DAgger rounds in disrupted runs from guided's weights and no PPO step (its
    card says so). In a disrupted validation shop where guided leaves the guide follower's run, it makes the
    follower's run (valid against the scenario). Like the follower it was cloned from (and as bench/disrupted.py
    --no-guide-replan compares them), it acts the start's plan out here: with re-plans its run also depends on
    what the re-plans find, which is not what cloning taught."""
    from fms_dispatch.full_rules import run_full
    from fms_dispatch.rl.guide import GuideFollower, effort_from
    from fms_dispatch.rl.models import load_config
    from fms_sim.env import check_disruptions, episode_scenario

    ref = resolve_model("guided-dagger")
    cfg = load_config(ref.folder)
    metrics = json.loads((ref.folder / "metrics.json").read_text())
    assert cfg["init"] == "models/guided" and cfg["disruptions"] and cfg["warm_start"]["dagger"] == 2
    assert metrics["ppo_steps"] == 0 and len(metrics["warm_start"]["dagger_rounds"]) == 2
    (inst,) = [i for i in expand_instances(["genbu:**3@31"]) if i.name == "bu3s31_01"]
    sc = episode_scenario(inst, check_disruptions({"noise": 0.2, "breakdowns": 1, "fixed": True, "seed": 0}))
    effort = effort_from(tabu=0.0)
    follower = run_full(inst, GuideFollower(effort=effort), sc)
    dagger = ppo_solver("ppo:guided-dagger")(inst, scenario=sc, guide_effort=effort, guide_replan=False)
    clone = ppo_solver("ppo:guided")(inst, scenario=sc, guide_effort=effort, guide_replan=False)
    assert validate(inst, dagger, sc) == [] and dagger.makespan == follower.makespan < clone.makespan
    replanned = ppo_solver("ppo:guided-dagger")(inst, scenario=sc, guide_effort=effort)
    assert validate(inst, replanned, sc) == [] and replanned.meta["replans"]


def test_train_refuses_shops_named_alike_and_resume_options_it_would_drop(tmp_path):
    # two gen: shops differing in their tool count got one name: metrics.json kept one result (and a wrong mean)
    with pytest.raises(ValueError, match="two shops of the train set are named 'gen6x4s1_00'"):
        train(dict(TINY, train=["gen:6x4x3*1@1", "gen:6x4x4*1@1"], steps=10), tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()
    # resume took every config key but steps and dropped it without a word; a damaged saved config was a traceback
    out = tmp_path / "m"
    out.mkdir()
    (out / "model.zip").write_bytes(b"")
    with pytest.raises(ValueError, match="the config gives only steps, not reward, seed"):
        train({"steps": 1, "reward": "makespan", "seed": 99}, out, resume=True, progress=False)
    for text in ('{"steps": ', "[1]", "\udcff"):
        (out / "config.json").write_text(text, errors="surrogateescape")
        with pytest.raises(ValueError, match=f"cannot resume: {out / 'config.json'}"):
            train({"steps": 1}, out, resume=True, progress=False)
