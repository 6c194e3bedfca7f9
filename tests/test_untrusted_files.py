"""Files a user can trust: crafted policy zips, datasets, checkpoints and specs run no code, read no file outside
themselves, never wait on a pipe and never inflate to gigabytes, through the public API and every command. Every
crafted file is made here (no binaries are committed); each refusal is one line naming the file and the entry or
field, exit status 2 from the CLI."""

from __future__ import annotations

import base64
import importlib.util
import json
import os
import pickle
import shutil
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from synthetic_dynamics import write_linear_dataset

from rwm_gym.cli import main
from rwm_gym.resources import assets_dir

SHIPPED_POLICY = sorted((assets_dir() / "policies").glob("*.zip"))[0]
SECRET = b"secret-bytes-from-outside-the-file"


def one_line(capsys, *words: str) -> str:
    """The command's stderr (progress bars aside) is one line without a traceback, holding `words`."""
    lines = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip() and "%|" not in ln]
    err = "\n".join(lines)
    assert len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err
    return err


def status(argv: list[str]) -> int:
    """`rwm-gym ARGV`'s exit status, whether `main` returns it or raises it (as `sys.exit` does)."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code


@pytest.fixture(scope="module")
def good_data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "good.h5", num_episodes=4)


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A file outside every input: what a crafted file would have rwm-gym read."""
    secret = tmp_path / "outside" / "secret.bin"
    secret.parent.mkdir()
    secret.write_bytes(SECRET * 64)
    return secret


# Datasets: HDF5 that reads other files or declares more than it holds -------------------------------------------


def _crafted(good: Path, out: Path, edit) -> Path:
    shutil.copy(good, out)
    with h5py.File(out, "a") as f:
        edit(f)
    return out


def _external_storage(secret: Path):
    def edit(f: h5py.File) -> None:
        rows = len(f["steps/reward"])
        f.create_dataset("steps/leak", shape=(rows,), dtype="u1", external=[(str(secret), 0, rows)])

    return edit


def _external_link(secret_h5: Path):
    def edit(f: h5py.File) -> None:
        f["steps/leak"] = h5py.ExternalLink(str(secret_h5), "/data")

    return edit


def _external_required_field(secret: Path):
    def edit(f: h5py.File) -> None:  # a required field itself kept in another file
        rows = len(f["steps/reward"])
        del f["steps/reward"]
        f.create_dataset("steps/reward", shape=(rows,), dtype="<f4", external=[(str(secret), 0, 4 * rows)])

    return edit


def _huge_unused_field(f: h5py.File) -> None:
    f.create_dataset("steps/unused", shape=(3 << 30,), dtype="u1", chunks=(1 << 20,))  # stores nothing


def _virtual(secret_h5: Path):
    def edit(f: h5py.File) -> None:
        layout = h5py.VirtualLayout(shape=(4,), dtype="f8")
        layout[:] = h5py.VirtualSource(str(secret_h5), "data", shape=(4,))
        f.create_virtual_dataset("steps/leak", layout)

    return edit


def _secret_h5(secret: Path) -> Path:
    out = secret.with_suffix(".h5")
    with h5py.File(out, "w") as f:
        f["data"] = np.frombuffer(SECRET[:32], dtype="f8")
    return out


BAD_DATASETS = {
    "external storage": (lambda s: _external_storage(s), ["field 'leak'", "another file"]),
    "external storage of a required field": (lambda s: _external_required_field(s), ["field 'reward'", "another"]),
    "external link": (lambda s: _external_link(_secret_h5(s)), ["field 'leak'", "links to"]),
    "virtual dataset": (lambda s: _virtual(_secret_h5(s)), ["field 'leak'", "virtual"]),
    "declared 3 GiB": (lambda s: _huge_unused_field, ["field 'unused'", "declares"]),
}


@pytest.mark.parametrize("case", BAD_DATASETS)
def test_a_dataset_that_reads_other_files_or_declares_gigabytes_is_refused_before_reading(
    tmp_path, good_data, outside, case
) -> None:
    from rwm_gym.data.dataset import Dataset, DatasetError

    make, words = BAD_DATASETS[case]
    bad = _crafted(good_data, tmp_path / "bad.h5", make(outside))
    with pytest.raises(DatasetError) as err:
        Dataset.load(bad)
    assert "\n" not in str(err.value) and str(bad) in str(err.value)
    for word in words:
        assert word in str(err.value)


@pytest.mark.parametrize("case", ["external storage", "external link", "declared 3 GiB"])
def test_train_and_export_refuse_such_a_dataset_in_one_line(tmp_path, good_data, outside, capsys, case) -> None:
    make, words = BAD_DATASETS[case]
    bad = _crafted(good_data, tmp_path / "bad.h5", make(outside))
    args = ["--iterations", "1", "--history", "4", "--forecast", "2", "--batch-size", "4", "--hidden-size", "8"]
    assert status(["train", "--data", str(bad), "--out", str(tmp_path / "m.safetensors"), *args, "--quiet"]) == 2
    one_line(capsys, str(bad), *words)
    assert not (tmp_path / "m.safetensors").exists()
    if importlib.util.find_spec("minari"):
        assert status(["export", "--minari", str(bad), "--out", str(tmp_path / "minari")]) == 2
        one_line(capsys, str(bad), *words)
        assert not (tmp_path / "minari").exists()


def test_a_dataset_path_that_is_a_fifo_is_refused_without_waiting(tmp_path) -> None:
    from rwm_gym.data.dataset import Dataset, DatasetError

    fifo = tmp_path / "data.h5"
    os.mkfifo(fifo)
    with pytest.raises(DatasetError, match="not a regular file"):
        Dataset.load(fifo)


def test_a_soft_link_inside_the_file_and_compressed_fields_still_load(tmp_path, good_data) -> None:
    from rwm_gym.data.dataset import Dataset

    def edit(f: h5py.File) -> None:
        f["alias"] = h5py.SoftLink("/steps/reward")
        f.create_dataset("steps/zeros", data=np.zeros(len(f["steps/reward"]), np.float32), compression="gzip")

    ds = Dataset.load(_crafted(good_data, tmp_path / "ok.h5", edit))
    assert "zeros" in ds.fields and not ds["zeros"].any()


@pytest.fixture(scope="module")
def good_minari(good_data, tmp_path_factory) -> Path:
    pytest.importorskip("minari")
    out = tmp_path_factory.mktemp("minari") / "m"
    assert status(["export", "--minari", str(good_data), "--out", str(out)]) == 0
    return out


def _minari_copy(good: Path, tmp_path: Path, edit) -> Path:
    folder = tmp_path / "m"
    shutil.copytree(good, folder)
    with h5py.File(folder / "main_data.hdf5", "a") as f:
        edit(f["episode_0"])
    return folder


@pytest.mark.parametrize("case", ["external storage", "external link", "declared 3 GiB"])
def test_import_refuses_a_minari_file_that_reads_other_files(tmp_path, good_minari, outside, capsys, case) -> None:
    def edit(group: h5py.Group) -> None:
        if case == "external storage":
            group.create_dataset("infos/leak", shape=(len(SECRET),), dtype="u1", external=[(str(outside), 0, 34)])
        elif case == "external link":
            group["infos/leak"] = h5py.ExternalLink(str(_secret_h5(outside)), "/data")
        else:
            group.create_dataset("infos/leak", shape=(3 << 30,), dtype="u1", chunks=(1 << 20,))

    folder = _minari_copy(good_minari, tmp_path, edit)
    assert status(["import", "--minari", str(folder), "--out", str(tmp_path / "back.h5")]) == 2
    one_line(capsys, "main_data.hdf5", "episode_0/infos/leak")
    assert not (tmp_path / "back.h5").exists()


def test_import_refuses_a_minari_file_that_links_out_of_its_folder(tmp_path, good_minari, capsys) -> None:
    folder = tmp_path / "m"
    shutil.copytree(good_minari, folder)
    elsewhere = tmp_path / "elsewhere.hdf5"
    (folder / "main_data.hdf5").rename(elsewhere)
    (folder / "main_data.hdf5").symlink_to(elsewhere)
    assert status(["import", "--minari", str(folder), "--out", str(tmp_path / "back.h5")]) == 2
    one_line(capsys, "main_data.hdf5", "link")


# Policy zips: pickles that would run code ------------------------------------------------------------------------


def _payloads(marker: Path) -> dict[str, bytes]:
    """Hand-assembled pickles, each running `touch marker` when unpickled: every way a pickle names and calls."""
    cmd = f"touch {marker}".encode()
    argv = pickle.dumps(["sh", "-c", cmd.decode()], protocol=2)[2:-1]  # a list, without PROTO and STOP
    text = b"\x8c" + bytes([len(cmd)]) + cmd  # SHORT_BINUNICODE
    return {
        # protocol 4: an allowed module with a dotted attribute path that walks to subprocess.Popen
        "dotted STACK_GLOBAL": b"\x80\x04\x95\x00\x00\x00\x00\x00\x00\x00\x00"
        + b"\x8c\x1btorch.nn.modules.activation\x8c\x1aF.np.f2py.subprocess.Popen\x93"
        + argv
        + b"\x85R.",
        "protocol 5 STACK_GLOBAL": b"\x80\x05\x8c\x05posix\x8c\x06system\x93" + text + b"\x85R.",
        "protocol 0 GLOBAL + REDUCE": b"cposix\nsystem\n(V" + cmd + b"\ntR.",
        "dotted GLOBAL (protocol 4)": b"\x80\x04cos\npath.os.system\n(V" + cmd + b"\ntR.",
        "INST": b"(V" + cmd + b"\niposix\nsystem\n.",
        "OBJ": b"\x80\x02(cposix\nsystem\nV" + cmd + b"\no.",
        # NEWOBJ / NEWOBJ_EX build str(system(cmd)): the class is harmless, its argument is a call
        "NEWOBJ": b"\x80\x02cbuiltins\nstr\ncposix\nsystem\n" + text + b"\x85R\x85\x81.",
        "NEWOBJ_EX": b"\x80\x04\x8c\x08builtins\x8c\x03str\x93\x8c\x05posix\x8c\x06system\x93"
        + text
        + b"\x85R\x85}\x92.",
        "BUILD": b"\x80\x02cposix\nsystem\n" + text + b"\x85R}b.",
    }


def _live(payload: bytes, marker: Path) -> bool:
    """Whether plain `pickle.loads` runs the payload (it must, or the test below proves nothing)."""
    import subprocess

    try:
        result = pickle.loads(payload)
        if isinstance(result, subprocess.Popen):
            result.wait()
    except Exception:
        pass
    ran = marker.exists()
    marker.unlink(missing_ok=True)
    return ran


def _policy_with(folder: Path, edit) -> Path:
    evil = folder / "evil.zip"
    with zipfile.ZipFile(SHIPPED_POLICY) as src, zipfile.ZipFile(evil, "w") as out:
        for info in src.infolist():
            payload = src.read(info)
            if info.filename == "data":
                data = json.loads(payload)
                edit(data)
                payload = json.dumps(data).encode()
            out.writestr(info, payload)
    return evil


@pytest.mark.parametrize("opcodes", list(_payloads(Path("m"))))
def test_no_crafted_pickle_runs_wherever_it_sits_in_a_policy_zip(tmp_path, opcodes) -> None:
    from rwm_gym.policy_zip import PolicyFileError, load_policy

    marker = tmp_path / "ran"
    payload = _payloads(marker)[opcodes]
    assert _live(payload, marker), f"the {opcodes} payload does not run under plain pickle"
    encoded = base64.b64encode(payload).decode()
    obs = np.random.default_rng(0).normal(size=(8, 48)).astype(np.float32)
    reference = load_policy(SHIPPED_POLICY).predict(obs, deterministic=True)[0]

    def hidden(data: dict) -> None:  # the pickle swapped in, every readable field kept; plus one in a new key
        for key in ("policy_class", "observation_space", "action_space", "policy_kwargs", "lr_schedule", "clip_range"):
            data[key][":serialized:"] = encoded
        data["data"] = {":type:": "<class 'object'>", ":serialized:": encoded}
        data["_last_obs"] = {":type:": "<class 'numpy.ndarray'>", ":serialized:": encoded}

    loaded = load_policy(_policy_with(tmp_path, hidden))
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], reference)
    for key in ("policy_class", "observation_space", "policy_kwargs", "lr_schedule"):

        def bare(data: dict, key=key) -> None:  # the entry is the pickle alone
            data[key] = {":type:": "<class 'object'>", ":serialized:": encoded}

        with pytest.raises(PolicyFileError, match=f"entry '{key}'") as err:
            load_policy(_policy_with(tmp_path, bare))
        assert "\n" not in str(err.value) and "evil.zip" in str(err.value)
    assert not marker.exists()


@pytest.mark.parametrize(
    "key, value, words",
    [
        ("policy_kwargs", {"activation_fn": "<class 'torch.nn.modules.activation.F.np.f2py.subprocess.Popen'>"}, []),
        ("policy_kwargs", {"features_extractor_class": "<class 'subprocess.Popen'>"}, ["features extractor"]),
        ("policy_kwargs", {"optimizer_class": "<class 'os.system'>"}, ["optimizer"]),
        ("policy_kwargs", {"net_arch": [100000, 100000]}, ["layer sizes"]),
        ("policy_kwargs", {"net_arch": [4096, 4096, 4096]}, ["parameters", "policy.pth"]),
        ("policy_kwargs", {"device": "cpu", "squash_output": "yes"}, ["true or false"]),
        ("policy_kwargs", {"lambda": 1}, ["'lambda'"]),
        (
            "policy_kwargs",
            {"features_extractor_kwargs": {"mean": [0.0] * 48, "std": [1.0] * 48, "task": "../../etc/passwd"}},
            ["not an env id"],
        ),
        ("n_steps", 1e400, ["n_steps"]),
        ("n_envs", 10**9, ["rollout buffer"]),
        ("clip_range", {":type:": "<class 'stable_baselines3.common.utils.FloatSchedule'>", "value_schedule": "x"}, []),
        ("tensorboard_log", "/etc", None),  # ignored: a log folder is the user's to give
    ],
)
def test_the_policy_is_rebuilt_only_from_fields_it_checks(tmp_path, key, value, words) -> None:
    from rwm_gym.policy_zip import PolicyFileError, load_policy

    def edit(data: dict) -> None:
        if key == "policy_kwargs":
            data[key] = {**{k: v for k, v in data[key].items() if k != ":serialized:"}, **value}
        else:
            data[key] = value

    path = _policy_with(tmp_path, edit)
    if words is None:
        assert load_policy(path).tensorboard_log is None
        return
    with pytest.raises(PolicyFileError, match=f"entry '{key}'" if key != "n_envs" else "n_envs") as err:
        load_policy(path)
    assert "\n" not in str(err.value)
    for word in words:
        assert word in str(err.value)


@pytest.mark.parametrize("opcodes", ["dotted STACK_GLOBAL", "protocol 0 GLOBAL + REDUCE", "INST"])
@pytest.mark.parametrize("where", ["policy_class", "data"])
def test_commands_given_a_crafted_policy_run_nothing(tmp_path, capsys, opcodes, where) -> None:
    marker = tmp_path / "ran"
    encoded = base64.b64encode(_payloads(marker)[opcodes]).decode()

    def edit(data: dict) -> None:
        data[where] = {":type:": "<class 'object'>", ":serialized:": encoded}

    evil = _policy_with(tmp_path, edit)
    out = tmp_path / "score"
    code = status(
        ["score", "--policy", str(evil), "--out", str(out), "--seeds", "1", "--commands", "0", "--steps", "2"]
    )
    if where == "policy_class":  # a field the policy is built from: refused
        assert code == 2
        one_line(capsys, "evil.zip", "entry 'policy_class'")
    else:  # a key the policy is not built from: never decoded
        assert code == 0
    assert not marker.exists()


def test_a_policy_zip_bomb_is_refused_before_it_inflates(tmp_path, capsys) -> None:
    from rwm_gym.policy_zip import PolicyFileError, load_policy

    bomb = tmp_path / "bomb.zip"
    with zipfile.ZipFile(SHIPPED_POLICY) as src, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as out:
        for info in src.infolist():
            if info.filename != "policy.optimizer.pth":
                out.writestr(info.filename, src.read(info))
        with out.open("policy.optimizer.pth", "w", force_zip64=True) as member:
            zeros = bytes(1 << 20)
            for _ in range(64):
                member.write(zeros)
    assert bomb.stat().st_size < 1 << 20
    with pytest.raises(PolicyFileError, match=r"'policy\.optimizer\.pth' would inflate") as err:
        load_policy(bomb)
    assert "\n" not in str(err.value)
    out = tmp_path / "score"
    assert status(["score", "--policy", str(bomb), "--out", str(out), "--seeds", "1", "--steps", "2"]) == 2
    one_line(capsys, "bomb.zip", "inflate")


def test_a_zip_member_that_inflates_past_its_declared_size_stops_there(tmp_path) -> None:
    from rwm_gym.untrusted import read_zip_member

    path = tmp_path / "liar.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as out:
        out.writestr("data", b"x" * 4096)
    raw = bytearray(path.read_bytes())
    central = raw.rindex(b"PK\x01\x02")
    raw[central + 24 : central + 28] = (100).to_bytes(4, "little")  # the central directory's uncompressed size
    path.write_bytes(bytes(raw))
    with zipfile.ZipFile(path) as archive, pytest.raises((ValueError, zipfile.BadZipFile)):
        data = read_zip_member(archive, archive.getinfo("data"), 1 << 20)
        assert len(data) <= 100


# Specs and checkpoints: a model path that leads out, a FIFO, a header asking for gigabytes -----------------------


def _spec_text(model: str) -> str:
    return _shipped_text().replace('model = "anymal_d/scene.xml"', f"model = {json.dumps(model)}", 1)


def _shipped_text() -> str:
    from rwm_gym.resources import specs_dir

    return (specs_dir() / "anymal_d.toml").read_text()


@pytest.fixture(scope="module")
def checkpoint(good_data, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ckpt") / "m.safetensors"
    args = ["--iterations", "1", "--history", "4", "--forecast", "2", "--batch-size", "4", "--hidden-size", "8"]
    limits = ["--joint-limits", "--unit-gravity", "--num-layers", "1", "--quiet"]  # the constraints read the MJCF
    assert status(["train", "--data", str(good_data), "--out", str(out), *args, *limits]) == 0
    return out


def _crafted_checkpoint(source: Path, out: Path, *, spec_text: str | None = None, **config) -> Path:
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(source), framework="pt") as f:
        header, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    meta = json.loads(header["meta"])
    if spec_text is not None:
        meta["spec"] = spec_text
    meta["model_config"].update(config)
    save_file(tensors, str(out), metadata={**header, "meta": json.dumps(meta)})
    return out


def _fifo(folder: Path, name: str) -> Path:
    path = folder / name
    os.mkfifo(path)
    return path


OUT_OF_TREE = {
    "absolute": lambda tmp, secret: str(secret),
    "dot-dot": lambda tmp, secret: "../" * 12 + str(secret).lstrip("/"),
    "dot-dot from an asset": lambda tmp, secret: "anymal_d/../../" + "../" * 12 + str(secret).lstrip("/"),
    "fifo": lambda tmp, secret: str(_fifo(tmp, "model.xml")),
}


@pytest.mark.parametrize("case", OUT_OF_TREE)
def test_a_spec_from_a_checkpoint_or_dataset_names_only_the_package_models(tmp_path, outside, case) -> None:
    from rwm_gym.spec import parse_spec

    spec = parse_spec(_spec_text(OUT_OF_TREE[case](tmp_path, outside)), where="ckpt:spec")
    with pytest.raises(ValueError, match="outside rwm-gym's assets") as err:
        _ = spec.model_path
    assert "\n" not in str(err.value)
    assert parse_spec(_spec_text(str(assets_dir() / "anymal_d" / "scene.xml"))).model_path.is_file()


@pytest.mark.parametrize("case", OUT_OF_TREE)
def test_gym_make_on_a_crafted_checkpoint_opens_no_outside_file(
    tmp_path, outside, checkpoint, monkeypatch, case
) -> None:
    import gymnasium as gym
    import mujoco

    opened = []
    for name in ("from_xml_path", "from_xml_string"):
        real = getattr(mujoco.MjModel, name)
        monkeypatch.setattr(mujoco.MjModel, name, lambda *a, _real=real: opened.append(a) or _real(*a))
    crafted = _crafted_checkpoint(
        checkpoint,
        tmp_path / "c.safetensors",
        spec_text=_spec_text(OUT_OF_TREE[case](tmp_path, outside)),
    )
    env = gym.make("rwm_gym:Imagined-v0", checkpoint=str(crafted))  # the limits are the file's own buffers
    env.reset(seed=0)
    env.step(env.action_space.sample())
    assert opened == []
    drawn = gym.make("rwm_gym:Imagined-v0", checkpoint=str(crafted), render_mode="rgb_array")
    drawn.reset(seed=0)
    with pytest.raises(ValueError, match="outside rwm-gym's assets") as err:
        drawn.render()
    assert "\n" not in str(err.value) and opened == []


def _user_robot(folder: Path, scene: str) -> Path:
    """A spec file of the user's with its model beside it, as `rwm-gym spec --mjcf` writes them."""
    robot = folder / "robot"
    robot.mkdir(parents=True)
    shutil.copy(assets_dir() / "anymal_d" / "anymal_d.xml", robot / "anymal_d.xml")
    (robot / "scene.xml").write_text(scene)
    spec = robot / "robot.toml"
    spec.write_text(_spec_text(str(robot / "scene.xml")))
    return spec


def test_a_user_spec_file_names_a_model_beside_it_but_no_include_outside(tmp_path, outside) -> None:
    from rwm_gym.spec import load_spec

    scene = (assets_dir() / "anymal_d" / "scene.xml").read_text()
    good = load_spec(_user_robot(tmp_path / "a", scene))
    assert good.model_path == tmp_path / "a" / "robot" / "scene.xml"
    relative = (tmp_path / "a" / "robot" / "robot.toml").read_text().replace(str(good.model_path), "scene.xml")
    (tmp_path / "a" / "robot" / "relative.toml").write_text(relative)
    assert load_spec(tmp_path / "a" / "robot" / "relative.toml").model_path == good.model_path
    for include, words in (
        (str(outside), "absolute path"),
        ("../../outside/secret.bin", "leads out"),
        ("nested.xml", "absolute path"),  # nested.xml includes the secret in its turn
    ):
        (tmp_path / "b").mkdir(exist_ok=True)
        shutil.rmtree(tmp_path / "b" / "robot", ignore_errors=True)
        spec_file = _user_robot(tmp_path / "b", scene.replace('file="anymal_d.xml"', f'file="{include}"'))
        (spec_file.parent / "nested.xml").write_text(f'<mujoco><include file="{outside}"/></mujoco>')
        with pytest.raises(ValueError, match=words) as err:
            _ = load_spec(spec_file).model_path
        assert "\n" not in str(err.value)


def test_a_model_or_include_that_is_a_fifo_is_refused_without_waiting(tmp_path) -> None:
    from rwm_gym.spec import load_spec

    scene = (assets_dir() / "anymal_d" / "scene.xml").read_text()
    spec_file = _user_robot(tmp_path, scene.replace('file="anymal_d.xml"', 'file="pipe.xml"'))
    _fifo(spec_file.parent, "pipe.xml")
    with pytest.raises(ValueError, match="FIFO"):
        _ = load_spec(spec_file).model_path
    fifo_model = spec_file.with_name("fifo.toml")
    fifo_model.write_text(_spec_text(str(_fifo(spec_file.parent, "model.xml"))))
    with pytest.raises(ValueError, match="FIFO"):
        _ = load_spec(fifo_model).model_path


def test_a_checkpoint_whose_header_asks_for_120_gb_is_refused_before_allocating(tmp_path, checkpoint, capsys) -> None:
    import gymnasium as gym

    from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint

    crafted = _crafted_checkpoint(checkpoint, tmp_path / "c.safetensors", hidden_size=100_000, num_layers=1)
    with pytest.raises(CheckpointError, match="GB of weights") as err:
        load_checkpoint(crafted)
    assert "\n" not in str(err.value)
    with pytest.raises(CheckpointError, match="GB of weights"):
        gym.make("rwm_gym:Imagined-v0", checkpoint=str(crafted))
    fitting = _crafted_checkpoint(checkpoint, tmp_path / "d.safetensors", hidden_size=4096)
    with pytest.raises(CheckpointError, match="has shape"):  # within memory, but not the file's tensors
        load_checkpoint(fitting)


def test_commands_refuse_a_model_include_or_input_fifo_in_one_line(tmp_path, outside, good_data, capsys) -> None:
    from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint

    scene = (assets_dir() / "anymal_d" / "scene.xml").read_text()
    spec_file = _user_robot(tmp_path, scene.replace('file="anymal_d.xml"', f'file="{outside}"'))
    collect = ["collect", "--policy", "random", "--episodes", "1", "--max-steps", "2", "--num-envs", "1"]
    assert status([*collect, "--env", str(spec_file), "--out", str(tmp_path / "d.h5")]) == 2
    one_line(capsys, "<include file>", "absolute path")
    fifo = _fifo(tmp_path, "data.h5")
    assert status(["train", "--data", str(fifo), "--out", str(tmp_path / "m.safetensors"), "--quiet"]) == 2
    one_line(capsys, "data.h5", "not a regular file")
    with pytest.raises(CheckpointError, match="not a regular file"):
        load_checkpoint(_fifo(tmp_path, "m.safetensors"))
    from rwm_gym.policy_zip import PolicyFileError, load_policy

    with pytest.raises(PolicyFileError, match="FIFO"):
        load_policy(_fifo(tmp_path, "p.zip"))


def test_ppo_init_policy_refuses_a_crafted_zip_and_runs_nothing(tmp_path, capsys) -> None:
    marker = tmp_path / "ran"
    encoded = base64.b64encode(_payloads(marker)["protocol 5 STACK_GLOBAL"]).decode()

    def edit(data: dict) -> None:
        data["policy_class"] = {":type:": "<class 'object'>", ":serialized:": encoded}

    evil = _policy_with(tmp_path, edit)
    tiny = ["--num-envs", "2", "--n-steps", "8", "--timesteps", "16", "--no-eval"]
    assert status(["ppo", "--in", "physics", "--init-policy", str(evil), "--out", str(tmp_path / "p.zip"), *tiny]) == 2
    one_line(capsys, "evil.zip", "entry 'policy_class'")
    assert not marker.exists() and not (tmp_path / "p.zip").exists()


def test_json_nested_too_deep_is_refused_in_one_line(tmp_path, checkpoint) -> None:
    from safetensors import safe_open
    from safetensors.torch import save_file

    from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint
    from rwm_gym.policy_zip import PolicyFileError, load_policy

    deep = "[" * 100_000 + "]" * 100_000
    path = tmp_path / "deep.zip"
    with zipfile.ZipFile(path, "w") as out:
        out.writestr("data", deep)
        out.writestr("policy.pth", b"")
    with pytest.raises(PolicyFileError, match="not JSON"):
        load_policy(path)
    with safe_open(str(checkpoint), framework="pt") as f:
        header, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    save_file(tensors, str(tmp_path / "deep.safetensors"), metadata={**header, "meta": deep})
    with pytest.raises(CheckpointError, match="metadata unreadable"):
        load_checkpoint(tmp_path / "deep.safetensors")
    from rwm_gym.spec import parse_spec

    with pytest.raises(ValueError, match="nested too deep"):
        parse_spec("a = " + deep, where="data.h5:spec")
