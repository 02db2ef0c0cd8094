"""Bad input at every entry point: CLI, viewer uploads, and fuzzed files fed to the parsers (issue 9).

The library-level cases that tests/test_motion.py, tests/test_garments.py and tests/test_checkpoint.py already
cover (empty / junk / truncated BVH, NaN / non-manifold / huge OBJ, tampered / pickled / mis-shaped checkpoints)
are not repeated here. This file covers what is left:

- the same bad files through the command line (``smln.cli.main``): one line on stderr, exit status 2, no
  traceback, and nothing on disk is overwritten or left half-written;
- the same bad files through the viewer's upload validation (``app.uploads.UploadStore``): one-line
  :class:`~app.uploads.UploadError`, nothing kept in the upload folder;
- a pickle whose payload would create a marker file, renamed to a checkpoint: refused, and the marker proves
  that no code ran;
- BVH files with missing channels, absurd or negative frame counts, NaN/Inf channel values;
- property-based fuzzing (hypothesis) of the BVH and OBJ parsers: mutated copies of real files give either a
  result or the library's own error type, never another exception.
"""

from __future__ import annotations

import os
import pickle
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from app.uploads import MAX_BVH_BYTES, MAX_OBJ_BYTES, UploadError, UploadStore
from smln.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from smln.cli import main as cli_main
from smln.garments import Garment, GarmentError
from smln.model import SMLN, SMLNConfig
from smln.motion import MotionError, load_bvh
from smln.motion.library import clip_path

ROOT = Path(__file__).resolve().parent.parent
WALK = clip_path("02_01_walk")
SHAPE = "female_average"
FUZZ_EXAMPLES = int(os.environ.get("SMLN_FUZZ_EXAMPLES", "60"))
"""Hypothesis examples per fuzz test (bounded: the whole file stays well under a minute; raise it with
``SMLN_FUZZ_EXAMPLES`` and ``SMLN_FUZZ_SEED`` for a longer exploration)."""
FUZZ_OUTCOMES: Counter[str] = Counter()
"""Outcomes of the fuzz cases (printed at the end of the module with ``-s``)."""


# ---- helpers ------------------------------------------------------------------------------------------------------
def _walk_text() -> str:
    return WALK.read_text()


def _bvh_with_frames(n: int) -> str:
    """The shipped walk clip cut to its first ``n`` motion lines (header's ``Frames:`` updated)."""
    head, _, rest = _walk_text().partition("Frames:")
    lines = rest.splitlines()
    return head + f"Frames: {n}\n" + lines[1] + "\n" + "\n".join(lines[2 : 2 + n]) + "\n"


def _bvh_with_value(n: int, value: str, line: int = 4, column: int = 4) -> str:
    """The walk clip cut to ``n`` frames with one channel value of one motion line replaced by ``value``."""
    lines = _bvh_with_frames(n).splitlines()
    k = next(i for i, text in enumerate(lines) if text.startswith("Frame Time")) + 1 + line
    numbers = lines[k].split()
    numbers[column] = value
    lines[k] = " ".join(numbers)
    return "\n".join(lines) + "\n"


def _small_garment_obj() -> bytes:
    """A real generated garment (shorts, coarse) as OBJ text: small enough to fuzz quickly."""
    import trimesh

    from smln.garments import build_garment

    g = build_garment("shorts", edge_length=0.05)
    return trimesh.Trimesh(g.vertices, g.faces, process=False).export(file_type="obj").encode()


def _assert_one_line(message: str) -> None:
    message = message.strip()
    assert message, "empty error message"
    assert "\n" not in message, f"error message is not one line: {message!r}"
    assert "Traceback" not in message


def _tiny_checkpoint(stem: Path) -> Path:
    torch.manual_seed(0)
    save_checkpoint(stem, SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1)))), card={"variant": "full"})
    return stem


class _Marker:
    """Unpickling this runs ``Path(path).touch()``: evidence that a loader executed pickle code."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):  # noqa: ANN204 - pickle protocol
        return (Path.touch, (Path(self.path),))


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``smln ARGV`` in-process; returns (exit status, stdout, stderr). A traceback fails the test."""
    try:
        code = cli_main(argv)
    except SystemExit as exc:  # argparse usage errors
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def garment_obj() -> bytes:
    return _small_garment_obj()


@pytest.fixture()
def store(tmp_path: Path) -> UploadStore:
    s = UploadStore(tmp_path / "uploads")
    yield s
    s.close()


# ---- library: BVH cases the motion tests do not cover -----------------------------------------------------------
def test_bvh_missing_channels_is_refused(tmp_path: Path) -> None:
    """A joint that declares fewer channels than its motion lines carry (or a missing CHANNELS line)."""
    text = _walk_text()
    cases = {
        "fewer": text.replace("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 2 Zrotation Yrotation", 1),
        "none": re.sub(r"\n\s*CHANNELS 3 Zrotation Yrotation Xrotation", "", text, count=1),
    }
    for name, content in cases.items():
        path = tmp_path / f"{name}.bvh"
        path.write_text(content)
        with pytest.raises(MotionError) as err:
            load_bvh(path)
        _assert_one_line(str(err.value))
        assert path.name in str(err.value)


@pytest.mark.parametrize("frames, message", [("-5", "frame"), ("0", "frame"), ("12abc", "unreadable frame count"),
                                             ("99999999999999999999", "over the limit")])
def test_bvh_bad_frame_counts(tmp_path: Path, frames: str, message: str) -> None:
    head, _, rest = _walk_text().partition("Frames:")
    path = tmp_path / "frames.bvh"
    path.write_text(head + f"Frames: {frames}\n" + rest.split("\n", 1)[1])
    with pytest.raises(MotionError, match=message) as err:
        load_bvh(path)
    _assert_one_line(str(err.value))


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e400"])
def test_bvh_non_finite_channels(tmp_path: Path, value: str) -> None:
    path = tmp_path / "nan.bvh"
    path.write_text(_bvh_with_value(20, value))
    with pytest.raises(MotionError, match="NaN|infinite|parse") as err:
        load_bvh(path)
    _assert_one_line(str(err.value))


def test_bvh_over_the_size_limit(tmp_path: Path) -> None:
    """Over the library's 64 MB limit: refused from the size alone (a sparse file, nothing is read)."""
    from smln.motion.bvh import MAX_BVH_BYTES as LIB_LIMIT

    path = tmp_path / "huge.bvh"
    with open(path, "wb") as fh:
        fh.write(b"HIERARCHY\n")
        fh.truncate(LIB_LIMIT + 1)
    with pytest.raises(MotionError, match="limit") as err:
        load_bvh(path)
    _assert_one_line(str(err.value))


# ---- library: checkpoints ----------------------------------------------------------------------------------------
def test_pickle_renamed_to_checkpoint_runs_no_code(tmp_path: Path) -> None:
    """A malicious pickle with a valid card: refused, and its payload (touch a marker file) never ran."""
    stem = _tiny_checkpoint(tmp_path / "ck")
    marker = tmp_path / "PWNED"
    payload = pickle.dumps(_Marker(marker))
    assert not marker.exists()
    for data in (payload, b"junk" * 4 + payload):
        (tmp_path / "ck.safetensors").write_bytes(data)
        with pytest.raises(CheckpointError) as err:
            load_checkpoint(stem)
        _assert_one_line(str(err.value))
    # the same with torch's zip format wrapping the pickle
    torch.save({"x": _Marker(marker)}, tmp_path / "ck.safetensors")
    with pytest.raises(CheckpointError, match="zip"):
        load_checkpoint(stem)
    assert not marker.exists(), "loading the pickle executed its payload"
    # sanity: the payload does work when unpickled, so its absence above means something
    pickle.loads(payload)
    assert marker.exists()


def test_tampered_card_shapes_and_empty_files(tmp_path: Path) -> None:
    stem = _tiny_checkpoint(tmp_path / "ck")
    tensors, card = tmp_path / "ck.safetensors", tmp_path / "ck.json"
    good_tensors, good_card = tensors.read_bytes(), card.read_text()
    cases: dict[str, tuple[bytes, str]] = {
        "empty tensors": (b"", good_card),
        "empty card": (good_tensors, ""),
        "truncated tensors": (good_tensors[: len(good_tensors) // 2], good_card),
        "junk tensors": (os.urandom(4096), good_card),
        "card is a list": (good_tensors, "[1, 2]"),
        "bad config": (good_tensors, good_card.replace('"latent_size": 16', '"latent_size": "big"')),
    }
    for name, (t, c) in cases.items():
        tensors.write_bytes(t)
        card.write_text(c)
        with pytest.raises(CheckpointError) as err:
            load_checkpoint(stem)
        assert "\n" not in str(err.value).strip(), name


# ---- CLI ---------------------------------------------------------------------------------------------------------
def test_cli_bad_bvh_gives_one_line_and_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cases = {"empty.bvh": b"", "junk.bvh": os.urandom(2048), "trunc.bvh": WALK.read_bytes()[:30_000],
             "nan.bvh": _bvh_with_value(10, "nan").encode()}
    for name, data in cases.items():
        bvh = tmp_path / name
        bvh.write_bytes(data)
        out = tmp_path / f"{name}.npz"
        code, _, err = run_cli(["body", "--motion", str(bvh), "--out", str(out)], capsys)
        assert code == 2, (name, err)
        _assert_one_line(err)
        assert err.startswith("smln body: error:") and name in err
        assert not out.exists(), f"{name}: a failed run left {out}"


def test_cli_missing_file_and_unknown_names(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.npz"
    for argv in (["body", "--motion", str(tmp_path / "nothing.bvh"), "--out", str(out)],
                 ["body", "--motion", "no_such_clip", "--out", str(out)],
                 ["outfit", "no_such_outfit", "--out", str(tmp_path / "x.obj")]):
        code, _, err = run_cli(argv, capsys)
        assert code == 2, (argv, err)
        _assert_one_line(err)
        assert not out.exists()


def test_cli_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--out`` naming an existing file without ``--force``: refused, the file keeps its bytes."""
    for sub, argv in (
        ("body", ["body", "--motion", "05_01_walk", "--frames", "3"]),
        ("outfit", ["outfit", "tshirt_jacket"]),
        ("export", ["export", str(tmp_path / "whatever.npz"), "--format", "pc2"]),
        ("rollout", ["rollout", "--skinning", "--outfit", "tshirt_jacket", "--motion", "05_01_walk", "--frames", "3"]),
    ):
        out = tmp_path / f"precious_{sub}.npz"
        out.write_bytes(b"keep me")
        code, _, err = run_cli([*argv, "--out", str(out)], capsys)
        assert code == 2, (sub, err)
        _assert_one_line(err)
        assert "exists" in err and "--force" in err
        assert out.read_bytes() == b"keep me"


@pytest.mark.parametrize("argv", [["body", "--motion", "05_01_walk", "--frames", "3"],
                                  ["rollout", "--skinning", "--outfit", "tshirt_jacket", "--motion", "05_01_walk",
                                   "--frames", "3"]], ids=["body", "rollout"])
def test_cli_out_without_npz_suffix_does_not_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       argv: list[str]) -> None:
    """``--out result`` writes ``result.npz`` (numpy adds the suffix): an existing ``result.npz`` is protected too,
    and without one the message names the file really written."""
    (tmp_path / "result.npz").write_bytes(b"keep me")
    code, _, err = run_cli([*argv, "--out", str(tmp_path / "result")], capsys)
    assert (tmp_path / "result.npz").read_bytes() == b"keep me", f"smln {argv[0]} overwrote result.npz"
    assert code == 2 and "--force" in err
    _assert_one_line(err)
    (tmp_path / "result.npz").unlink()
    code, out, err = run_cli([*argv, "--out", str(tmp_path / "result")], capsys)
    assert code == 0, err
    assert f"wrote {tmp_path / 'result.npz'}" in out and (tmp_path / "result.npz").is_file()


def test_cli_bad_checkpoints(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Tampered (one byte flipped), pickled, mis-shaped and missing checkpoints through ``smln rollout``/``eval``:
    one line, exit 2, no output file, and no pickle payload executed."""
    stem = _tiny_checkpoint(tmp_path / "ck")
    tensors, card = tmp_path / "ck.safetensors", tmp_path / "ck.json"
    good = tensors.read_bytes()
    marker = tmp_path / "PWNED"

    def flipped() -> None:
        data = bytearray(good)
        data[len(data) // 2] ^= 0x01
        tensors.write_bytes(bytes(data))

    def pickled() -> None:
        tensors.write_bytes(pickle.dumps(_Marker(marker)))

    def wrong_shapes() -> None:
        tensors.write_bytes(good)
        card.write_text(card.read_text().replace('"latent_size": 16', '"latent_size": 32'))

    def missing() -> None:
        tensors.unlink()

    for name, damage in (("flipped", flipped), ("pickle", pickled), ("shapes", wrong_shapes), ("missing", missing)):
        damage()
        out = tmp_path / f"{name}.npz"
        for argv in (["rollout", "--checkpoint", str(stem), "--outfit", "tshirt_jacket", "--motion", "05_01_walk",
                      "--frames", "3", "--out", str(out)],
                     ["eval", "--checkpoint", str(stem), "--outfits", "tshirt_jacket", "--motions", "05_01_walk",
                      "--frames", "3"]):
            code, _, err = run_cli(argv, capsys)
            assert code == 2, (name, argv[0], err)
            _assert_one_line(err)
            assert err.startswith(f"smln {argv[0]}: error:")
        assert not out.exists()
    assert not marker.exists()


def test_cli_export_bad_rollout_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    marker = tmp_path / "PWNED"
    cases = {"empty.npz": b"", "junk.npz": os.urandom(1000), "pickle.npz": pickle.dumps(_Marker(marker))}
    # an npz holding an object array (np.load with allow_pickle would run it)
    obj = tmp_path / "objarr.npz"
    np.savez(obj, positions=np.array([_Marker(marker)], dtype=object))
    cases["objarr.npz"] = obj.read_bytes()
    for name, data in cases.items():
        src = tmp_path / name
        src.write_bytes(data)
        out = tmp_path / f"{name}.pc2"
        code, _, err = run_cli(["export", str(src), "--format", "pc2", "--out", str(out)], capsys)
        assert code == 2, (name, err)
        _assert_one_line(err)
        assert not out.exists()
    assert not marker.exists()


@pytest.mark.slow
def test_cli_subprocess_has_no_traceback(tmp_path: Path) -> None:
    """The installed entry point as a user runs it: a binary-junk BVH gives one stderr line and status 2."""
    bad = tmp_path / "junk.bvh"
    bad.write_bytes(os.urandom(512))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "smln.cli", "body", "--motion", str(bad), "--out",
                           str(tmp_path / "o.npz")], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    assert proc.returncode == 2, proc.stderr
    _assert_one_line(proc.stderr)
    assert "junk.bvh" in proc.stderr and not (tmp_path / "o.npz").exists()


# ---- viewer uploads ----------------------------------------------------------------------------------------------
def _refused(store: UploadStore, kind: str, name: str, data: bytes, match: str | None = None) -> str:
    add = store.add_bvh if kind == "bvh" else store.add_obj
    with pytest.raises(UploadError, match=match) as err:
        add(name, data, SHAPE)
    message = str(err.value)
    _assert_one_line(message)
    assert list(store.directory.iterdir()) == [], f"{name}: a refused upload was kept"
    assert store.clips() == [] and store.garments() == []
    return message


def test_upload_bvh_bad_files(store: UploadStore) -> None:
    walk = WALK.read_bytes()
    text = _walk_text()
    cases = {
        "junk.bvh": (os.urandom(4096), None),
        "trunc.bvh": (walk[: len(walk) // 3], None),
        "nan.bvh": (_bvh_with_value(10, "nan").encode(), None),
        "absurd.bvh": ((text.partition("Frames:")[0] + "Frames: 999999999\nFrame Time: 0.008333\n0 0\n").encode(),
                       "over the limit"),
        "channels.bvh": (text.replace("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 2 Zrotation Yrotation",
                                      1).encode(), None),
        "two_frames.bvh": (_bvh_with_frames(2).encode(), None),
        "huge.bvh": (b"HIERARCHY\n" + b" " * MAX_BVH_BYTES, "limit"),
    }
    for name, (data, match) in cases.items():
        msg = _refused(store, "bvh", name, data, match)
        assert name in msg


def test_upload_obj_bad_files(store: UploadStore, garment_obj: bytes) -> None:
    import trimesh

    mesh = trimesh.load(trimesh.util.wrap_as_stream(garment_obj), file_type="obj", process=False, force="mesh")
    floating = trimesh.Trimesh(mesh.vertices + [0.0, 0.0, 1.0], mesh.faces, process=False).export(file_type="obj")
    nan = garment_obj.replace(b"\nv ", b"\nv nan ", 1)
    inf = garment_obj.replace(b"\nv ", b"\nv inf ", 1)
    cases = {
        "empty.obj": (b"", "empty"),
        "junk.obj": (os.urandom(4096), None),
        "trunc.obj": (garment_obj[: len(garment_obj) // 3], None),
        "floating.obj": (floating.encode(), "on the body in its T-pose"),
        "nan.obj": (nan, None),
        "inf.obj": (inf, None),
        "nonmanifold.obj": (b"v 0 0 0\nv 0.3 0 0\nv 0 0.3 0\nv 0 0 0.3\nv 0.3 0.3 0.3\nf 1 2 3\nf 1 2 4\nf 1 2 5\n",
                            "non-manifold"),
        "points.obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", None),
        "badindex.obj": (b"v 0 0 0\nv 0.3 0 0\nv 0 0.3 0\nf 1 2 99\n", None),
        "huge.obj": (b"v 0 0 0\n" + b"#" * MAX_OBJ_BYTES, "limit"),
        "manyverts.obj": (b"v 0.1 0.2 0.3\n" * 60_000 + b"f 1 2 3\n", "limit"),
    }
    for name, (data, match) in cases.items():
        msg = _refused(store, "obj", name, data, match)
        assert name in msg


def test_upload_obj_in_centimetres_and_y_up_is_read_and_said(store: UploadStore, garment_obj: bytes) -> None:
    """A garment exported as Blender and Maya write OBJ (Y up, centimetres) is accepted, fitted where the metre
    Z-up file is, and the store says how it was read (the viewer shows it in its notification)."""
    import trimesh

    from smln.garments.obj_import import UP_AXES

    mesh = trimesh.load(trimesh.util.wrap_as_stream(garment_obj), file_type="obj", process=False, force="mesh")
    y_up_cm = trimesh.Trimesh(np.asarray(mesh.vertices) @ UP_AXES["y"] * 100, mesh.faces, process=False)
    key = store.add_obj("shorts_cm.obj", y_up_cm.export(file_type="obj").encode(), SHAPE)
    plain = store.add_obj("shorts.obj", garment_obj, SHAPE)
    assert store.note(key) == "read in cm, turned from Y up to Z up" and store.note(plain) == ""
    np.testing.assert_allclose(store.cloth(key, SHAPE).rest_vertices, store.cloth(plain, SHAPE).rest_vertices,
                               atol=1e-5)


def test_upload_keeps_accepted_state(store: UploadStore, garment_obj: bytes) -> None:
    """A refused upload after an accepted one leaves the accepted one (the viewer keeps its current scene)."""
    key = store.add_obj("shorts.obj", garment_obj, SHAPE)
    before = sorted(store.directory.iterdir())
    with pytest.raises(UploadError):
        store.add_obj("shorts.obj", b"v 1 2 3\n", SHAPE)
    assert store.garments() == [(key, "shorts")] and sorted(store.directory.iterdir()) == before
    assert store.cloth(key, SHAPE).num_vertices > 0


def test_upload_names_cannot_escape_the_folder(store: UploadStore, tmp_path: Path) -> None:
    """A hostile file name (path traversal) is written inside the upload folder only."""
    name = "../../../" + "evil.bvh"
    key = store.add_bvh(name, WALK.read_bytes(), SHAPE)
    path = store.clip_path(key).resolve()
    assert path.parent == store.directory.resolve()
    assert not (tmp_path.parent / "evil.bvh").exists()


# ---- fuzzing -----------------------------------------------------------------------------------------------------
WALK_BYTES = WALK.read_bytes()
WALK_LINES = WALK_BYTES.split(b"\n")
NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
REPLACEMENTS = [b"nan", b"inf", b"-inf", b"0", b"-1", b"1e308", b"99999999999", b"", b"x", b"3.", b"--1", b"1e-400"]


@st.composite
def mutated_bytes(draw: st.DrawFn, base: bytes, lines: list[bytes]) -> bytes:
    """One to three mutations of ``base``: byte flips, truncation, line deletions/duplications, number swaps."""
    data = base
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["flip", "truncate", "delete_lines", "duplicate_line", "number", "insert"]))
        if kind == "flip":
            buf = bytearray(data or b" ")
            for _ in range(draw(st.integers(1, 8))):
                i = draw(st.integers(0, len(buf) - 1))
                buf[i] = draw(st.integers(0, 255))
            data = bytes(buf)
        elif kind == "truncate":
            data = data[: draw(st.integers(0, max(len(data) - 1, 0)))]
        elif kind in ("delete_lines", "duplicate_line"):
            ls = data.split(b"\n")
            i = draw(st.integers(0, max(len(ls) - 1, 0)))
            # bias towards the header, where the structure lives
            if draw(st.booleans()):
                i = min(i, draw(st.integers(0, min(len(ls) - 1, 200))))
            n = draw(st.integers(1, 5))
            ls = ls[:i] + ls[i + n :] if kind == "delete_lines" else ls[: i + 1] + ls[i : i + 1] * n + ls[i + 1 :]
            data = b"\n".join(ls)
        elif kind == "number":
            matches = list(NUMBER.finditer(data[:20_000] if draw(st.booleans()) else data))
            if matches:
                m = matches[draw(st.integers(0, len(matches) - 1))]
                data = data[: m.start()] + draw(st.sampled_from(REPLACEMENTS)) + data[m.end() :]
        else:
            i = draw(st.integers(0, len(data)))
            data = data[:i] + draw(st.binary(min_size=1, max_size=16)) + data[i:]
    return data


_SEED = os.environ.get("SMLN_FUZZ_SEED")
FUZZ_SETTINGS = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=_SEED is None, database=None,
                         suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module", autouse=True)
def _report_fuzz_outcomes() -> None:
    yield
    if FUZZ_OUTCOMES:
        print("\nfuzz outcomes:", dict(sorted(FUZZ_OUTCOMES.items())))


def _seeded(test):  # noqa: ANN001, ANN202 - decorator
    return seed(int(_SEED))(test) if _SEED is not None else test


@_seeded
@FUZZ_SETTINGS
@given(data=mutated_bytes(WALK_BYTES, WALK_LINES))
def test_fuzz_bvh_parser(tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    """Mutated copies of a shipped clip: ``load_bvh`` either returns a finite clip or raises MotionError."""
    path = tmp_path_factory.mktemp("fuzz") / "mutant.bvh"
    path.write_bytes(data)
    try:
        clip = load_bvh(path)
    except MotionError as exc:
        _assert_one_line(str(exc))
        FUZZ_OUTCOMES["bvh: MotionError"] += 1
        return
    FUZZ_OUTCOMES["bvh: loaded"] += 1
    assert clip.num_frames > 0
    assert np.isfinite(clip.local_rotations).all() and np.isfinite(clip.root_positions).all()
    # what the CLI and the viewer do next: retarget onto the body (resampled to 30 fps)
    from smln.body import load_body
    from smln.motion import retarget

    try:
        motion = retarget(clip, load_body(SHAPE))
    except MotionError as exc:
        _assert_one_line(str(exc))
        FUZZ_OUTCOMES["bvh: loaded, retarget MotionError"] += 1
        return
    FUZZ_OUTCOMES["bvh: loaded and retargeted"] += 1
    assert torch.isfinite(motion.world_orientations).all() and torch.isfinite(motion.root_positions).all()


_OBJ_BASE = _small_garment_obj()


@_seeded
@FUZZ_SETTINGS
@given(data=mutated_bytes(_OBJ_BASE, _OBJ_BASE.split(b"\n")))
def test_fuzz_obj_importer(tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    """Mutated copies of a real garment OBJ: ``Garment.from_obj`` returns a finite garment or raises GarmentError."""
    from smln.body import load_body

    path = tmp_path_factory.mktemp("fuzz") / "mutant.obj"
    path.write_bytes(data)
    try:
        g = Garment.from_obj(path, load_body(SHAPE))
    except GarmentError as exc:
        _assert_one_line(str(exc))
        FUZZ_OUTCOMES["obj: GarmentError"] += 1
        return
    FUZZ_OUTCOMES["obj: loaded"] += 1
    assert g.num_vertices > 0 and np.isfinite(g.vertices).all()
    assert np.isfinite(g.skin_weights).all() and np.isfinite(g.vertex_mass).all()


def test_fuzz_inputs_are_real(tmp_path: Path) -> None:
    """The unmutated fuzz seeds load (so the fuzzers start from valid files)."""
    from smln.body import load_body

    assert load_bvh(WALK).num_frames > 100
    path = tmp_path / "seed.obj"
    path.write_bytes(_OBJ_BASE)
    assert Garment.from_obj(path, load_body(SHAPE)).num_vertices > 50


@pytest.mark.slow
def test_viewer_keeps_its_scene_on_refused_uploads(garment_obj: bytes) -> None:
    """Refused uploads through the viewer's own upload callbacks: a one-line notification to the browser that
    sent it, the setting and the computed frames stay as they were."""
    import socket
    from types import SimpleNamespace

    from app.server import ViewerApp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    app = ViewerApp(port=port, checkpoint_dir=None, max_frames=5)
    notes: list[tuple[str, str, object]] = []
    app.notify = lambda title, body, client=None, error=True: notes.append((title, body, client))  # type: ignore[method-assign]
    try:
        assert app.worker.wait_frames(5, timeout=120)
        setting, scenario = app.setting, app.worker.scenario
        browser = object()
        uploads = [("bvh", "junk.bvh", os.urandom(3000)), ("bvh", "nan.bvh", _bvh_with_value(10, "nan").encode()),
                   ("obj", "junk.obj", os.urandom(3000)), ("obj", "points.obj", b"v 0 0 0\n"),
                   ("obj", "big.obj", b"#" * (MAX_OBJ_BYTES + 1))]
        for kind, name, data in uploads:
            event = SimpleNamespace(target=SimpleNamespace(value=SimpleNamespace(name=name, content=data)),
                                    client=browser)
            (app._on_upload_bvh if kind == "bvh" else app._on_upload_obj)(event)
            title, body, client = notes[-1]
            assert "refused" in title and name in body and client is browser
            _assert_one_line(body)
            assert app.setting == setting and app.worker.scenario is scenario
        assert len(notes) == len(uploads)
        assert app.uploads.clips() == [] and app.uploads.garments() == []
        assert list(app.uploads.directory.iterdir()) == []
    finally:
        app.stop()


def _real_rollout_arrays() -> dict[str, np.ndarray]:
    """The arrays of a real rollout NPZ (3 skinned frames of a 2-layer outfit, coarse), as ``np.load`` gives them."""
    import io

    from smln.data_sampling import make_scene
    from smln.evaluate import skinning_frames
    from smln.export import save_rollout_npz

    scene = make_scene("tshirt_jacket", SHAPE, "09_06_run", edge_length=0.05, max_frames=3)
    buf = io.BytesIO()
    save_rollout_npz(buf, list(skinning_frames(scene, 3)), scene.cloth, scene.body.faces,
                     meta={"outfit": "tshirt_jacket", "clip": "09_06_run", "shape": SHAPE})
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


_ROLLOUT = _real_rollout_arrays()
_WEIRD_VALUES = [np.nan, np.inf, -1, 2**31 - 1, 1e30, 0]


@st.composite
def mutated_rollout(draw: st.DrawFn) -> dict[str, np.ndarray]:
    """A real rollout's arrays with 1-3 of them deleted, reshaped, retyped or filled with odd values."""
    arrays = dict(_ROLLOUT)
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(_ROLLOUT)))
        kind = draw(st.sampled_from(["delete", "shape", "scalar", "string", "fill", "truncate", "dtype"]))
        a = arrays.get(key, _ROLLOUT[key])
        if kind == "delete":
            arrays.pop(key, None)
        elif kind == "shape":
            shape = tuple(draw(st.lists(st.integers(0, 4), max_size=4)))
            arrays[key] = np.zeros(shape, dtype=a.dtype if a.dtype.kind != "U" else np.float32)
        elif kind == "scalar":
            arrays[key] = np.array(draw(st.sampled_from(_WEIRD_VALUES)))
        elif kind == "string":
            arrays[key] = np.array(draw(st.sampled_from(["", "{", "[1, 2]", "null", "x" * 100, '{"outfit": 3}'])))
        elif kind == "fill" and a.size and a.dtype.kind in "fiub":
            b = a.astype(np.float64).copy()
            idx = draw(st.integers(0, b.size - 1))
            b.flat[idx] = draw(st.sampled_from(_WEIRD_VALUES))
            arrays[key] = b.astype(a.dtype) if a.dtype.kind == "f" or np.isfinite(b).all() else b
        elif kind == "truncate" and a.ndim:
            arrays[key] = a[: draw(st.integers(0, max(len(a) - 1, 0)))]
        elif kind == "dtype" and a.dtype.kind != "U":
            arrays[key] = a.astype(draw(st.sampled_from([np.int8, np.float16, np.bool_, np.complex64])))
    return arrays


@_seeded
@FUZZ_SETTINGS
@given(arrays=mutated_rollout())
def test_fuzz_rollout_npz(tmp_path_factory: pytest.TempPathFactory, arrays: dict[str, np.ndarray]) -> None:
    """Structure-aware fuzzing of rollout NPZs (``smln export`` input, viewer rollout uploads): the library's
    ``load_rollout_npz`` gives a rollout or ExportError, and what it accepts exports to OBJ and PC2; the viewer's
    ``load_extra`` gives a saved rollout or ExtraRolloutError."""
    import io
    import warnings

    from app.extras import ExtraRolloutError, load_extra
    from smln.export import ExportError, export_bytes, load_rollout_npz

    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        np.savez_compressed(buf, **arrays)
    data = buf.getvalue()
    try:
        r = load_rollout_npz(io.BytesIO(data))
    except ExportError as exc:
        _assert_one_line(str(exc))
        FUZZ_OUTCOMES["npz: ExportError"] += 1
    else:
        FUZZ_OUTCOMES["npz: loaded"] += 1
        for fmt in ("obj", "pc2"):
            try:
                export_bytes(r, fmt)
            except ExportError:
                FUZZ_OUTCOMES[f"npz: {fmt} ExportError"] += 1
    try:
        load_extra(data, "extra:1", "fuzz.npz")
    except ExtraRolloutError as exc:
        _assert_one_line(str(exc))
        FUZZ_OUTCOMES["npz: viewer refused"] += 1
    else:
        FUZZ_OUTCOMES["npz: viewer accepted"] += 1
