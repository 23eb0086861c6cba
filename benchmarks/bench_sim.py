"""Speed of the synthetic data engine (issue 3), with its references, in one run.

    python benchmarks/bench_sim.py [--object 003_cracker_box] [--renders 200]
                                   [--duration 2.0] [--presets regular faster]
                                   [--device cpu] [--skip-end-to-end] [--ycb-dir DIR]

Target: a 2 s, 640x480, 500 FPS sequence (1001 renders) in under 60 s on 2 cores.

Rows:
  * render: frames/s of :class:`evtrack.sim.renderer.Renderer` at 640x480 for a YCB mesh
    (16k triangles, 2048² texture) in the benchmark scene, including the one read-back of
    RGB + depth + mask per frame; reference: a bare moderngl loop (a ~2.3k-triangle textured
    mesh, RGBA8 read-back, no background), the setting of the issue's 220 frames/s figure.
  * event simulation: frames/s of :class:`evtrack.sim.esim.EventSimulator` on the log
    frames of the same renders (1 torch thread, as the engine runs it; torch's default threads;
    CUDA if present); reference: the plain per-pixel loop (:func:`simulate_reference`) on a
    crop, scaled to a 640x480 frame.
  * end to end: :func:`evtrack.sim.engine.simulate` writing a full sequence, per stage.

Timings on a shared machine are noisy (the development machine has 2 cores shared by four
engineers); the load average is printed with the results. Rerun when the machine is quiet.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from evtrack.sim.config import EventConfig, SimConfig
from evtrack.sim.engine import preset_config, sequence_scene, sequence_trajectory, simulate
from evtrack.sim.esim import EventSimulator, log_intensity, simulate_reference
from evtrack.sim.objects import make_bottle, resolve_object
from evtrack.sim.renderer import Renderer, create_gl_context, gl_projection

TARGET_S = 60.0
CROP = (40, 30)  # per-pixel reference runs on this crop


def _load() -> str:
    try:
        one, five, fifteen = os.getloadavg()
        return f"load average {one:.1f} {five:.1f} {fifteen:.1f}"
    except OSError:  # pragma: no cover
        return "load average n/a"


def bench_render(obj, cfg: SimConfig, n: int) -> tuple[float, list[np.ndarray]]:
    """Frames/s of the engine's renderer; also returns the log frames for the event rows."""
    cam = cfg.camera.camera()
    traj = sequence_trajectory(cfg, obj)
    times = np.arange(n + 1) / cfg.render.render_hz
    poses = traj.pose(times)
    logs = []
    with Renderer(cam, cfg.render.near, cfg.render.far) as r:
        sequence_scene(cfg).apply(r)
        r.set_object(obj)
        r.render_raw(poses[0])
        t0 = time.perf_counter()
        for P in poses[1:]:
            r.render_raw(P)
        fps = n / (time.perf_counter() - t0)
        for P in poses:
            raw = r.render_raw(P)
            logs.append(log_intensity(torch.from_numpy(raw[..., :3].copy()),
                                      cfg.events.log_eps))
    return fps, logs


def bench_render_reference(cfg: SimConfig, n: int) -> tuple[float, int]:
    """A bare moderngl loop: textured mesh, RGBA8 read-back, nothing else."""
    import moderngl

    mesh = make_bottle(seed=0)
    cam = cfg.camera.camera()
    ctx = create_gl_context()
    try:
        prog = ctx.program(
            vertex_shader="""#version 330
            uniform mat4 mvp; in vec3 in_pos; in vec2 in_uv; out vec2 uv;
            void main() { uv = in_uv; gl_Position = mvp * vec4(in_pos, 1.0); }""",
            fragment_shader="""#version 330
            uniform sampler2D tex; in vec2 uv; out vec4 color;
            void main() { color = texture(tex, uv); }""")
        data = np.hstack([mesh.vertices, mesh.uv]).astype("f4")
        vao = ctx.vertex_array(prog, [(ctx.buffer(data.tobytes()), "3f 2f", "in_pos", "in_uv")],
                               index_buffer=ctx.buffer(mesh.faces.astype("i4").tobytes()),
                               index_element_size=4)
        tex = ctx.texture(mesh.texture.shape[1::-1], 3, mesh.texture.tobytes())
        tex.build_mipmaps()
        tex.use(0)
        fbo = ctx.simple_framebuffer((cam.width, cam.height))
        fbo.use()
        ctx.enable(moderngl.DEPTH_TEST)
        proj = gl_projection(cam, 0.05, 20.0)
        buf = np.empty((cam.height, cam.width, 4), np.uint8)
        angles = np.linspace(0, 2 * np.pi, n + 1)

        def frame(a: float) -> None:
            T = np.eye(4)
            c, s = np.cos(a), np.sin(a)
            T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
            T[:3, 3] = [0.0, 0.0, 0.45]
            prog["mvp"].write((proj @ T).T.astype("f4").tobytes())
            fbo.clear(0.0, 0.0, 0.0, 1.0)
            vao.render()
            fbo.read_into(buf, components=4)

        frame(0.0)
        t0 = time.perf_counter()
        for a in angles[1:]:
            frame(a)
        return n / (time.perf_counter() - t0), len(mesh.faces)
    finally:
        ctx.release()


def bench_events(logs: list[torch.Tensor], cfg: EventConfig, device: str, threads: int | None
                 ) -> tuple[float, float]:
    """Frames/s and events per frame of the batched simulator."""
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        h, w = logs[0].shape
        sim = EventSimulator(w, h, cfg, seed=0, device=device)
        frames = [f.to(device) for f in logs]
        sim.reset(frames[0], 0)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        n_ev = 0
        t0 = time.perf_counter()
        for k, f in enumerate(frames[1:], start=1):
            n_ev += len(sim.step(f, k * 2000))
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        dt = time.perf_counter() - t0
    finally:
        torch.set_num_threads(before)
    return (len(frames) - 1) / dt, n_ev / (len(frames) - 1)


def bench_events_reference(logs: list[torch.Tensor], cfg: EventConfig, n: int) -> float:
    """The per-pixel loop on a crop around the image centre, as 640x480 frames/s."""
    h, w = logs[0].shape
    cw, ch = CROP
    y0, x0 = h // 2 - ch // 2, w // 2 - cw // 2
    frames = np.stack([f[y0:y0 + ch, x0:x0 + cw].numpy() for f in logs[:n + 1]]).astype(
        np.float64)
    c = np.full((ch, cw), cfg.threshold_on)
    t0 = time.perf_counter()
    simulate_reference(frames, np.arange(n + 1) * 2000, c, c, cfg.refractory_us)
    crop_fps = n / (time.perf_counter() - t0)
    return crop_fps * (cw * ch) / (w * h)


def bench_end_to_end(obj, cfg: SimConfig, preset: str) -> dict:
    cfg = preset_config(cfg, preset)
    with tempfile.TemporaryDirectory() as tmp:
        stats = simulate(obj, cfg, Path(tmp) / "seq", progress=False)
        size = sum(p.stat().st_size for p in (Path(tmp) / "seq").rglob("*") if p.is_file())
    return {"stats": stats, "bytes": size}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="003_cracker_box")
    ap.add_argument("--ycb-dir", type=Path, default=None)
    ap.add_argument("--renders", type=int, default=200, help="frames for the render/event rows")
    ap.add_argument("--duration", type=float, default=2.0, help="end-to-end sequence, seconds")
    ap.add_argument("--presets", nargs="+", default=["regular", "faster"])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--skip-end-to-end", action="store_true")
    args = ap.parse_args()

    cfg = dataclasses.replace(SimConfig(duration=args.duration, seed=1000))
    obj = resolve_object(args.object, ycb_dir=args.ycb_dir)
    cam = cfg.camera.camera()
    print(f"evtrack.sim speed, {cam.width}x{cam.height}, object {obj.name} "
          f"({len(obj.faces)} triangles, texture {obj.texture.shape[1]}x{obj.texture.shape[0]})")
    ctx = create_gl_context()
    print(f"GL renderer: {ctx.info['GL_RENDERER']}; torch {torch.__version__}; {_load()}")
    ctx.release()
    rows = []
    fps, logs = bench_render(obj, cfg, args.renders)
    ref_fps, ref_tris = bench_render_reference(cfg, args.renders)
    rows.append(("render + read-back (RGB, depth, mask), frames/s", f"{fps:8.1f}",
                 f"bare moderngl, {ref_tris} tris, RGBA8: {ref_fps:.1f}"))
    ev_cfg = cfg.events
    ev_fps, ev_per = bench_events(logs, ev_cfg, "cpu", 1)
    ref_ev = bench_events_reference(logs, ev_cfg, min(20, args.renders))
    rows.append((f"event simulation CPU 1 thread, frames/s ({ev_per:.0f} ev/frame)",
                 f"{ev_fps:8.1f}", f"per-pixel loop: {ref_ev:.2f}"))
    dflt = torch.get_num_threads()
    ev_fps2, _ = bench_events(logs, ev_cfg, "cpu", None)
    rows.append((f"event simulation CPU {dflt} threads (torch default), frames/s",
                 f"{ev_fps2:8.1f}", ""))
    if args.device.startswith("cuda"):
        ev_fps3, _ = bench_events(logs, ev_cfg, args.device, None)
        rows.append((f"event simulation {args.device}, frames/s", f"{ev_fps3:8.1f}", ""))
    width = max(len(r[0]) for r in rows) + 2
    print(f"\n{'what':{width}s}{'measured':>10s}  reference")
    for what, val, ref in rows:
        print(f"{what:{width}s}{val:>10s}  {ref}")
    if args.skip_end_to_end:
        return
    n_renders = int(round(args.duration * cfg.render.render_hz)) + 1
    print(f"\nend to end: {args.duration:g} s, {n_renders} renders at "
          f"{cfg.render.render_hz:g} FPS, 60 FPS RGB-D, events + flow ground truth "
          f"(target < {TARGET_S:.0f} s for 2 s)")
    stages = ("render", "events", "ground_truth", "frames", "write", "other")
    print(f"{'preset':9s}{'total s':>9s}{'events':>11s}{'MB':>7s}" +
          "".join(f"{s:>13s}" for s in stages) + "   vs target")
    for preset in args.presets:
        res = bench_end_to_end(obj, cfg, preset)
        st = res["stats"]
        tim = st.timings
        verdict = "OK" if tim["total"] < TARGET_S * args.duration / 2.0 else "over"
        print(f"{preset:9s}{tim['total']:9.1f}{st.num_events:11d}{res['bytes'] / 1e6:7.0f}" +
              "".join(f"{tim.get(s, 0.0):13.1f}" for s in stages) + f"   {verdict}")
    print(_load())


if __name__ == "__main__":
    main()
