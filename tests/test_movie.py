"""Movies of a view's frames (minority.movie) and `minority replay --movie`: MP4s decode back
to the frames given (count, size, colour within codec tolerance), odd sides are padded to
even, the animated WebP is animated and under its size bound; replay --movie makes one MP4
per view from the logged frames, or from a new spec's re-rendered frames only."""

import io

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image
from test_replay import (  # noqa: F401 - recorded: a fixture
    RECORDED,
    RUN,
    chunk,
    make_spec,
    recorded,
    view,
)

from minority.cli import main
from minority.movie import (
    ANIMATION_MAX_BYTES,
    ANIMATION_WIDTH,
    MovieError,
    padded,
    pick,
    write_animation,
    write_movies,
    write_mp4,
)
from minority.protocol import Frame
from minority.protocol.log import read_log

COLOURS = [(200, 30, 30), (30, 200, 30), (30, 30, 200), (128, 128, 128), (240, 220, 40)]
TOLERANCE = 6  # mean channel value, 0-255: what H.264 at the movie quality may move


def decoded(path) -> tuple[dict, list[np.ndarray]]:
    """The MP4's metadata and its frames [h, w, 3] uint8."""
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    return meta, [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]


def solid(rgb, w, h) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, np.uint8), (h, w, 3)).copy()


def png(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()


def animation(path) -> tuple[int, int, tuple[int, int]]:
    """An animated WebP's pictures (libwebp merges a picture equal to the one before into
    it), how long it shows them all (ms), and its size (px)."""
    with Image.open(path) as im:
        assert im.format == "WEBP" and im.is_animated
        shown = 0
        for k in range(im.n_frames):
            im.seek(k)
            im.load()  # the duration is read with the picture
            shown += im.info["duration"]
        return im.n_frames, shown, im.size


def test_mp4_holds_every_frame_at_its_size_and_colour(tmp_path):
    frames = [solid(c, 64, 48) for c in COLOURS]
    sources = [frames[0], png(frames[1]), tmp_path / "2.png", frames[3], png(frames[4])]
    Image.fromarray(frames[2]).save(tmp_path / "2.png")  # arrays, PNG bytes and files mix
    assert write_mp4(sources, tmp_path / "m.mp4", fps=5) == (64, 48)
    meta, got = decoded(tmp_path / "m.mp4")
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (64, 48) and meta["fps"] == 5 and meta["duration"] == pytest.approx(1)
    assert len(got) == len(COLOURS)
    for image, colour in zip(got, COLOURS, strict=True):  # in the order given
        np.testing.assert_allclose(image.reshape(-1, 3).mean(axis=0), colour, atol=TOLERANCE)


def test_odd_sides_are_padded_with_the_edge_not_cropped(tmp_path):
    image = solid((20, 20, 20), 49, 37)
    image[:, -1] = (230, 230, 230)  # a light last column
    image[-1, :-1] = (20, 20, 230)  # a blue last row
    small = solid((200, 30, 30), 30, 20)  # a smaller frame of the same view
    assert write_mp4([image, small, image], tmp_path / "odd.mp4") == (50, 38)
    meta, got = decoded(tmp_path / "odd.mp4")
    assert meta["size"] == (50, 38) and len(got) == 3
    first = got[0].astype(int)
    assert abs(first[:36, 48:].mean() - 230) < TOLERANCE * 2  # the last column, repeated
    assert np.abs(first[37, 8:40] - (20, 20, 230)).mean() < TOLERANCE * 2  # the last row
    np.testing.assert_allclose(first[:30, :40].reshape(-1, 3).mean(axis=0), (20, 20, 20),
                               atol=TOLERANCE)  # the frame itself, not scaled
    np.testing.assert_allclose(got[1][:18, :28].reshape(-1, 3).mean(axis=0), (200, 30, 30),
                               atol=TOLERANCE)
    exact = padded(image, 50, 38)  # the padding itself, before the codec
    np.testing.assert_array_equal(exact[:37, :49], image)
    np.testing.assert_array_equal(exact[:, 49], exact[:, 48])
    np.testing.assert_array_equal(exact[37], exact[36])


def test_bad_frames_and_paths_are_named(tmp_path):
    with pytest.raises(MovieError, match="no frames"):
        write_mp4([], tmp_path / "none.mp4")
    with pytest.raises(MovieError, match=r"not an image"):
        write_mp4([b"not a png"], tmp_path / "junk.mp4")
    with pytest.raises(MovieError, match=r"\[8, 8, 3\] float64"):  # found while encoding
        write_mp4([solid((0, 0, 0), 8, 8), np.zeros((8, 8, 3))], tmp_path / "float.mp4")
    assert not (tmp_path / "float.mp4").exists()  # no half movie left behind
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError):
        write_mp4([solid((0, 0, 0), 8, 8)], tmp_path / "file" / "m.mp4")  # a file as folder
    said = []
    with pytest.raises(MovieError, match="no frames to make movies of"):
        write_movies({"side": []}, tmp_path, progress=said.append)
    movies = write_movies({"side": [], "top": [solid((9, 9, 9), 8, 8)] * 2}, tmp_path,
                          animation=False, progress=said.append)
    assert [m.view for m in movies] == ["top"] and (tmp_path / "top.mp4").is_file()
    assert "movie side: no frames, no movie" in said and not (tmp_path / "side.mp4").exists()


def test_animation_is_small_animated_and_as_long_as_the_movie(tmp_path):
    rng = np.random.default_rng(0)  # noise: the hardest case for the size bound
    frames = [rng.integers(0, 256, (481, 641, 3), dtype=np.uint8) for _ in range(60)]
    n, size, nbytes = write_animation(frames, tmp_path / "a.webp", fps=10)
    assert nbytes == (tmp_path / "a.webp").stat().st_size <= ANIMATION_MAX_BYTES
    pictures, shown_ms, shape = animation(tmp_path / "a.webp")
    assert pictures == n > 1 and shape == size == (ANIMATION_WIDTH, 240)  # of 642x482 padded
    assert shown_ms == pytest.approx(6000, abs=n)  # 60 frames at 10 fps
    # a tighter bound: a lower quality, then fewer pictures, each shown longer
    n, size, nbytes = write_animation(frames, tmp_path / "b.webp", fps=10, max_bytes=150_000)
    pictures, shown_ms, _ = animation(tmp_path / "b.webp")
    assert nbytes <= 150_000 and 1 < pictures == n < 40
    assert shown_ms == pytest.approx(6000, abs=n)
    with pytest.raises(MovieError, match="does not fit in 1000 bytes"):
        write_animation(frames[:4], tmp_path / "c.webp", max_bytes=1000)


def test_pick_spreads_frames_and_keeps_both_ends():
    assert pick(5, 40) == [0, 1, 2, 3, 4] and pick(5, 1) == [0]
    got = pick(100, 10)
    assert len(got) == 10 and got[0] == 0 and got[-1] == 99
    assert max(np.diff(got)) - min(np.diff(got)) <= 1


def logged(log) -> dict:
    frames = [r.decode() for r in read_log(log, [f"minority/{RUN}/frame/*"])]
    return {(f.view, f.step): f.png for f in frames if isinstance(f, Frame)}


def test_replay_movie_takes_the_logged_frames(recorded, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "out"
    frames = logged(recorded / "run.mcap")
    assert main(["replay", str(recorded / "run.mcap"), "--movie", "--fps", "4",
                 "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "6 logged frames of 2 views written" in captured.out and "not re-rendered" in \
        captured.out
    assert "step 0" not in captured.err  # nothing re-rendered
    assert "movie side: encoding 3 frames" in captured.err  # a progress line per movie
    for name in ("side", "top"):
        meta, got = decoded(out / f"{name}.mp4")
        assert meta["size"] == (48, 36) and meta["fps"] == 4 and len(got) == 3
        for image, step in zip(got, (0, 20, 40), strict=True):
            source = frames[(name, step)]
            assert (out / name / f"{step:06d}.png").read_bytes() == source
            want = np.asarray(Image.open(io.BytesIO(source)).convert("RGB"))
            np.testing.assert_allclose(image.reshape(-1, 3).mean(axis=0),
                                       want.reshape(-1, 3).mean(axis=0), atol=TOLERANCE)
        pictures, shown_ms, shape = animation(out / f"{name}.webp")
        assert pictures > 1 and shown_ms == 750 and shape == (48, 36)  # 3 frames at 4 fps


def test_replay_movie_of_a_new_spec_takes_only_this_replays_frames(recorded, tmp_path,  # noqa: F811
                                                                   capsys):
    spec = make_spec(view("odd", field="displacement", width=49, height=37,
                          schedule=[{"every_steps": 20, "regions": ["left"]}]),
                     view("pressure", field="pressure",
                          schedule=[{"every_steps": 20, "regions": ["left"]}]))
    spec.save(tmp_path / "new.json")
    out = tmp_path / "out"
    (out / "odd").mkdir(parents=True)
    Image.fromarray(solid((255, 0, 0), 49, 37)).save(out / "odd" / "000099.png")  # stale
    assert main(["replay", str(recorded / "run.mcap"), "--spec", str(tmp_path / "new.json"),
                 "--movie", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "movie pressure: no frames, no movie" in captured.err
    assert "movie odd: 3 frames, 50x38" in captured.out
    meta, got = decoded(out / "odd.mp4")
    assert meta["size"] == (50, 38) and len(got) == 3  # 0, 20, 40; not the stale 99
    assert not (out / "pressure.mp4").exists()


def test_replay_movie_bad_input_and_failures(recorded, tmp_path, capsys):  # noqa: F811
    log = str(recorded / "run.mcap")
    spec = make_spec(view("pressure", field="pressure"))
    spec.save(tmp_path / "new.json")
    assert main(["replay", log, "--spec", str(tmp_path / "new.json"), "--movie", "-q",
                 "--out", str(tmp_path / "a")]) == 2
    assert "no frames to make movies of (views pressure)" in capsys.readouterr().err
    assert main(["replay", log, "--movie", "--fps", "0", "-q"]) == 2
    assert "--fps must be positive" in capsys.readouterr().err
    (tmp_path / "file").write_text("")  # --out names a file: nothing can be written there
    assert main(["replay", log, "--movie", "-q", "--out", str(tmp_path / "file")]) == 1
    assert "minority replay: error:" in capsys.readouterr().err


def test_replay_movie_of_a_log_without_frames_re_renders_it(tmp_path, capsys):
    from minority.protocol.log import LogWriter

    path = tmp_path / "sim.mcap"  # what `minority sim --record` logs: a spec and chunks
    with LogWriter(path) as log:
        log.write(RECORDED)
        for step in (0, 20, 40):
            for rank in range(2):
                log.write(chunk(step, rank))
    assert main(["replay", str(path), "--movie", "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    assert "no frames of run replay-run: re-rendering with its spec" in captured.err
    assert "3 steps replayed with the log's spec, 6 frames" in captured.out
    for name in ("side", "top"):
        meta, got = decoded(tmp_path / "out" / f"{name}.mp4")
        assert meta["size"] == (48, 36) and len(got) == 3


def test_replay_movie_says_which_views_logged_no_frame(tmp_path, capsys):
    from minority.protocol.log import LogWriter

    path = tmp_path / "frames.mcap"  # the spec's "top" view never got a frame
    colours = {0: (200, 30, 30), 20: (30, 30, 200)}
    with LogWriter(path) as log:
        log.write(RECORDED)
        for step in (20, 0, 20):  # out of order, and step 20 twice: its last frame counts
            log.write(Frame(RUN, "side", step, step * 1e-4, 49, 37,
                            png(solid(colours[step], 49, 37))))
            colours[20] = (30, 200, 30)
    assert main(["replay", str(path), "--movie", "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    assert "2 logged frames of 1 views" in captured.out
    assert "movie top: no frames, no movie" in captured.err
    meta, got = decoded(tmp_path / "out" / "side.mp4")
    assert meta["size"] == (50, 38) and len(got) == 2
    for image, colour in zip(got, [(200, 30, 30), (30, 200, 30)], strict=True):
        np.testing.assert_allclose(image.reshape(-1, 3).mean(axis=0), colour, atol=TOLERANCE)
    assert not (tmp_path / "out" / "top").exists() and not (tmp_path / "out" / "top.mp4").exists()
