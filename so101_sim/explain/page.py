"""The `so101-sim explain` page: one self-contained HTML (PNG figures embedded as base64) that
follows the seed walkthrough's eight steps with the numbers `explain.trace` recorded."""

from __future__ import annotations

import base64
import html
from typing import Any

import numpy as np

import so101_sim.explain.plots as plots

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;background:#f7f7f5;
color:#1d2329;line-height:1.45}
main{max-width:1180px;margin:0 auto;padding:24px 28px 60px}
h1{font-size:30px;margin:8px 0 4px}h2{font-size:22px;margin:0 0 4px}
section{background:#fff;border:1px solid #e2e2dd;border-radius:10px;padding:18px 22px;margin:18px 0}
.num{display:inline-block;background:#1d2329;color:#fff;border-radius:50%;width:30px;height:30px;
text-align:center;line-height:30px;margin-right:10px;font-weight:600}
.sub{color:#5a6570;margin:0 0 12px}.cards{display:flex;gap:12px;flex-wrap:wrap;margin:12px 0}
.card{background:#fff;border:1px solid #e2e2dd;border-radius:8px;padding:8px 14px;min-width:110px}
.card b{display:block;font-size:20px}.card span{color:#5a6570;font-size:12px}
table{border-collapse:collapse;margin:8px 0;font-size:13px}
td,th{border:1px solid #e2e2dd;padding:3px 8px;text-align:right}th{background:#f0f0ec}
td.l,th.l{text-align:left}tr.pad td{color:#a0a0a0}tr.exec td{background:#fffbe6}
code,.mono{font-family:ui-monospace,SFMono-Regular,Menlo,monospace;font-size:12.5px}
.box{background:#f3f6fa;border-left:4px solid #2b6cb0;padding:8px 12px;margin:10px 0}
.warn{background:#fff4ec;border-left:4px solid #e4572e;padding:8px 12px;margin:10px 0}
img{max-width:100%}.shape{color:#2b6cb0;font-weight:600}
"""


def _img(data: bytes, alt: str) -> str:
    return (f'<img alt="{html.escape(alt)}" src="data:image/png;base64,'
            f'{base64.b64encode(data).decode()}">')


def _f(v: float, nd: int = 3) -> str:
    return f"{v:.{nd}f}"


def _vec(v: list[float], nd: int = 3) -> str:
    return "[" + ", ".join(_f(x, nd) for x in v) + "]"


def _shape(s: list[int]) -> str:
    return f'<span class="shape">[{", ".join(str(x) for x in s)}]</span>'


def _section(n: int | str, title: str, sub: str, body: str) -> str:
    return (f'<section><h2><span class="num">{n}</span>{html.escape(title)}</h2>'
            f'<p class="sub">{sub}</p>{body}</section>')


def _table(head: list[str], rows: list[list[str]], classes: list[str] | None = None,
           left: int = 1) -> str:
    th = "".join(f'<th class="{"l" if i < left else ""}">{h}</th>' for i, h in enumerate(head))
    body = ""
    for r, row in enumerate(rows):
        cls = f' class="{classes[r]}"' if classes and classes[r] else ""
        body += f"<tr{cls}>" + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>'
                                        for i, c in enumerate(row)) + "</tr>"
    return f"<table><tr>{th}</tr>{body}</table>"


def _crops(n: dict, images: dict[str, np.ndarray], cam: str) -> tuple[list, list, list]:
    """Recorded frames, the policy crops and the crop boxes in recorded pixels, per obs step."""
    origs, crops, boxes = [], [], []
    for s in range(len(n["frames"]["steps"])):
        orig, pol = images[f"{cam}/orig/{s}"], images[f"{cam}/policy/{s}"]
        kp = n["encoder"]["keypoints"][f"{cam}/{s}"]
        ch, cw = n["encoder"]["crop_shape"]
        top, left = kp["crop_offset"] or (0, 0)
        crops.append(pol[top:top + ch, left:left + cw])
        box = kp["crop_box_policy"]
        sy, sx = orig.shape[0] / pol.shape[0], orig.shape[1] / pol.shape[1]
        boxes.append(None if box is None else [(box[0] + 0.5) * sx - 0.5,
                                               (box[1] + 0.5) * sy - 0.5,
                                               box[2] * sx, box[3] * sy])
        origs.append(orig)
    return origs, crops, boxes


def _header(n: dict) -> str:
    m, pol = n["meta"], n["meta"]["policy"]
    trained = pol.get("trained") or {}
    who = (f"checkpoint <code>{html.escape(pol['path'])}</code>" if pol["source"] == "checkpoint"
           else f"a freshly built, <b>untrained</b> <code>{html.escape(pol['name'])}</code> "
                "policy (normalisation stats from this dataset)")
    extra = (f" — preset {trained.get('preset')}, step {trained.get('step')}, "
             f"{trained.get('weights')} weights, trained on {trained.get('dataset_episodes')} "
             "episodes" if trained else "")
    size = m["dataset_image_size"]
    cards = [(m["episodes"], "episodes"), (f"{m['frames']:,}", "frames"), (m["fps"], "FPS"),
             (len(m["cameras"]), "cameras"),
             (f"{size[1]}×{size[0]}" if size else "?", "recorded resolution"),
             (f"{m['parameters'] / 1e6:.1f} M", "policy parameters")]
    card_html = "".join(f'<div class="card"><b>{v}</b><span>{lab}</span></div>'
                        for v, lab in cards)
    frames = " &amp; ".join(str(f) for f in m["obs_frames"])
    return (f"<h1>How this Diffusion Policy sees one training example</h1>"
            f'<p class="sub">Episode {m["episode"]}, frames {frames} of '
            f'<code>{html.escape(m["dataset"])}</code>, traced through {who}{extra}. Every '
            "number below was recorded from lerobot's own modules on this batch (forward hooks, "
            "the policy's scheduler and normaliser); the numbers are also in "
            "<code>explain.json</code>.</p>" + f'<div class="cards">{card_html}</div>')


def _steps_1_to_3(n: dict, images: dict[str, np.ndarray]) -> str:
    m, names = n["meta"], n["meta"]["joint_names"]
    steps, out = n["frames"]["steps"], []
    labels = [f"frame {f} ({s}, {t:.3f} s)" for f, s, t in zip(m["obs_frames"], steps,
                                                              m["obs_timestamps"], strict=True)]
    body = ""
    for key in m["cameras"]:
        cam = key.split(".")[-1]
        origs, crops, boxes = _crops(n, images, cam)
        pads = n["frames"]["is_pad"][cam]
        lab = [lb + (" — padding copy" if p else "") for lb, p in zip(labels, pads, strict=True)]
        body += f"<h3>{html.escape(key)}</h3>" + _img(plots.frames_figure(
            origs, crops, boxes, lab), f"{cam} frames")
    ph, pw = n["frames"]["policy_image_size"]
    ch, cw = n["encoder"]["crop_shape"]
    body += (f'<div class="box">Each recorded frame is resized to {ph}×{pw} by '
             "<code>so101_sim.utils.image_pipeline.resize_frames</code> (as in training and "
             f"evaluation), then the policy crops {ch}×{cw} (yellow box; the centre crop "
             "used at evaluation" + (" — training takes a random one" if m["config"][
                 "crop_is_random"] else "") + ").</div>")
    out.append(_section(1, f"The To = {len(steps)} observation frames",
                        "What each camera recorded and what the policy's encoder gets.", body))
    raw, norm = np.asarray(n["state"]["raw"]), np.asarray(n["state"]["normalised"])
    rows = [[html.escape(name), str(j)] + [_f(raw[s, j]) for s in range(len(steps))]
            + [f"{raw[-1, j] - raw[0, j]:+.3f}"] + [_f(norm[s, j]) for s in range(len(steps))]
            for j, name in enumerate(names)]
    head = ["joint", "index"] + [f"{s} (raw)" for s in steps] + ["Δ"] + [
        f"{s} (normalised)" for s in steps]
    body = _table(head, rows, left=1) + "".join(
        f"<p class=mono>s<sub>{s}</sub> = {_vec(raw[i])}</p>" for i, s in enumerate(steps))
    body += ("<p>Concatenated over the To frames: " f"{raw.size} values. The normaliser "
             "maps each joint to [-1, 1] with the dataset's min/max (MIN_MAX) before the "
             "network sees it.</p>")
    out.append(_section(2, "The proprioceptive state", "Joint positions in LeRobot units "
                        "(degrees; gripper 0..100) at each observation frame.", body))
    a = n["actions"]
    start, end = n["sampling"]["executed"]
    rows, cls = [], []
    for r, (vals, off, pad) in enumerate(zip(a["raw"], a["offsets"], a["is_pad"], strict=True)):
        rows.append([str(r), str(m["frame"] + off), html.escape(
            "t" if off == 0 else f"t{off:+d}") + (" (pad)" if pad else "")] +
            [_f(v) for v in vals])
        cls.append("pad" if pad else ("exec" if start is not None and start <= r < end else ""))
    body = _table(["row", "frame", "step"] + [html.escape(x) for x in names], rows, cls, left=3)
    body += (f'<div class="box">lerobot\'s chunk starts at the first observation frame, so row '
             f"{a['offsets'].index(0)} is frame t. Yellow rows ({start}..{end - 1}) are the "
             f"{end - start} actions executed at inference; grey rows are padding "
             "(copies of the episode's nearest action).</div>")
    out.append(_section(3, f"The Tp = {a['shape'][0]} actions to predict",
                        f"The action chunk A⁰, shape {_shape(a['shape'])} (leader-arm "
                        "targets, raw units).", body))
    return "".join(out)


def _step_4(n: dict, images: dict[str, np.ndarray]) -> str:
    e, m = n["encoder"], n["meta"]
    px = e["pixel"]
    norm = px["normaliser"] or {}
    body = "<h3>The traced pixel, through resize and normalisation</h3>" + _table(
        ["stage", "where", "R, G, B"], [
            ["recorded frame", f"(x={px['orig_xy'][0]}, y={px['orig_xy'][1]})",
             str(px["orig_rgb"])],
            ["resize_frames (uint8)", f"(x={px['policy_xy'][0]}, y={px['policy_xy'][1]})",
             str(px["policy_rgb"])],
            ["÷ 255", "", _vec(px["scaled"], 4)],
            [f"normaliser (x − mean) / std; mean {_vec(norm.get('mean', []))}, std "
             f"{_vec(norm.get('std', []))}", "", _vec(px["normalised"], 4)],
            ["centre of the crop", f"(x={px['crop_xy'][0]}, y={px['crop_xy'][1]})",
             _vec(e["stages"][0]["values"], 4)]], left=2)
    rows = []
    for st in e["stages"]:
        vals = (f"cell {tuple(st['cell'])}: {_vec(st['values'])} … ({st['channels']} ch)"
                if "cell" in st else (_vec(st["values"]) if st.get("values") else ""))
        rows.append([html.escape(st["name"]), html.escape(st["desc"]), _shape(st["shape"]),
                     vals])
    body += (f"<h3>Through the backbone ({html.escape(m['config']['vision_backbone'])}, "
             f"{html.escape(px['step'])} {html.escape(px['camera'])})</h3>") + _table(
        ["stage", "module", "shape", "first channels at the traced pixel"], rows, left=2)
    grid = e["feature_grid"]
    peak = e.get("attention_peak")
    body += (f'<div class="box">The last feature map is {grid[0]}×{grid[1]}: each of the '
             f"{e['n_keypoints']} keypoints is a softmax-weighted average of "
             f"{grid[0] * grid[1]} cell positions." + (
                 f" Mean peak attention {peak:.2f} (uniform would be "
                 f"{e['attention_uniform']:.2f}): " + (
                     "the keypoints mostly sit on single cells." if peak > 0.6 else
                     "the keypoints are spread between cells.") if peak is not None else "")
             + " A coordinate of −1 or +1 is the centre of the first or last cell (white lines "
               "on the crops); the 32 keypoints are coloured by index.</div>")
    body += "<h3>The spatial-softmax keypoints, drawn on each image</h3>"
    for key in m["cameras"]:
        cam = key.split(".")[-1]
        origs, crops, boxes = _crops(n, images, cam)
        kps = [e["keypoints"][f"{cam}/{s}"] for s in range(len(origs))]
        body += _img(plots.frames_figure(origs, crops, boxes, [
            f"{cam} {s}" for s in n["frames"]["steps"]], kps, tuple(grid)), f"{cam} keypoints")
    gc = e["global_cond"]
    rows = [[html.escape(seg["name"]), "?" if seg["start"] is None else
             f"{seg['start']}:{seg['end']}",
             "" if seg["start"] is None else str(seg["end"] - seg["start"])]
            for seg in gc["layout"]]
    body += (f"<h3>Global conditioning vector O<sub>t</sub>: {_shape(gc['shape'])}</h3>"
             "<p>Where each part sits, found by matching the recorded vector against the "
             f"parts (lerobot orders it per observation step; {e['feature_dim']} per image):</p>"
             + _table(["part", "slice", "length"], rows))
    for seg in gc["layout"]:
        if seg["name"].startswith("state") and seg["start"] is not None:
            body += (f"<p class=mono>O<sub>t</sub>[{seg['start']}:{seg['end']}] = "
                     f"{_vec(gc['values'][seg['start']:seg['end']])} ({html.escape(seg['name'])}"
                     ", normalised)</p>")
    return _section(4, "The ResNet encoder", "Shapes and values recorded by forward hooks on "
                    "every backbone stage and the spatial softmax.", body)


def _steps_5_to_7(n: dict) -> str:
    z, names, out = n["noise"], n["meta"]["joint_names"], []
    k, ab = z["k"], z["alpha_bar"]
    r = n["actions"]["offsets"].index(0)
    rows = [[html.escape(name), _f(z["clean"][r][j]), _f(z["eps"][r][j]),
             _f(z["scaled_clean"][r][j]), _f(z["scaled_eps"][r][j]), _f(z["noisy"][r][j])]
            for j, name in enumerate(names)]
    body = (f'<div class="box mono">A<sup>k</sup> = √ᾱ<sub>k</sub>·A⁰ + √(1−ᾱ<sub>k</sub>)·ε'
            f"; {html.escape(z['scheduler'])} ({html.escape(z['beta_schedule'])}): "
            f"ᾱ<sub>{k}</sub> = {ab:.5f}, √ᾱ = {ab ** 0.5:.5f}, √(1−ᾱ) = {(1 - ab) ** 0.5:.5f}"
            "</div><p>The noise is added to the <b>normalised</b> chunk (each joint in [-1, 1]),"
            f" here row {r} (frame t); A<sup>{k}</sup> is the scheduler's own "
            f"<code>add_noise</code> output (max |difference| from the formula "
            f"{z['add_noise_check']:.1e}).</p>")
    body += _table(["joint", "A⁰ (normalised)", "ε", "√ᾱ·A⁰", "√(1−ᾱ)·ε", f"A^{k}"], rows)
    body += _img(plots.alpha_bar_figure(z["alphas_cumprod"], k), "alpha bar")
    body += _img(plots.chunk_noise_figure(z["clean"], z["noisy"], names, k), "noisy chunk")
    out.append(_section(5, f"Adding noise at step k = {k}", "The forward diffusion, with the "
                        "policy's own noise scheduler.", body))
    t = n["timestep"]
    rows = [[html.escape(layer["name"]), _shape(layer["shape"])] for layer in t["layers"]]
    gc = n["encoder"]["global_cond"]["shape"][0]
    emb = t["embedding_shape"][0]
    body = (f"<p class=mono>sinusoidal(k={k})[:5] = {_vec(t['sinusoidal'][:5], 4)}</p>"
            + _table(["layer", "output shape"], rows)
            + f"<p class=mono>t_emb[:5] = {_vec(t['embedding'][:5], 4)}</p>"
            + f'<div class="box">Full conditioning = t_emb {_shape([emb])} + O<sub>t</sub> '
              f"{_shape([gc])} = {_shape(t['full_cond_shape'])} (read at the input of the first "
              f"FiLM layer, which maps it to {_shape(t['film_out_shape'])} = scale and bias for "
              "its channels).</div>"
            + _img(plots.embedding_figure(t["sinusoidal"], k), "embedding"))
    out.append(_section(6, "The diffusion-step embedding", "The integer k through the U-Net's "
                        "step encoder (recorded outputs).", body))
    u = n["unet"]
    rows = [[html.escape(b["name"]), html.escape(b["type"]), _shape(b["in"]), _shape(b["out"])]
            for b in u["blocks"]]
    body = (f"<p>Input A<sup>{k}</sup> {_shape(u['input'])} (channels first inside), output "
            f"ε<sub>θ</sub> {_shape(u['output'])}. Every block below was called once:</p>"
            + _table(["block", "module", "in", "out"], rows, left=2)
            + _img(plots.noise_pred_figure(n["loss"]["eps"], n["loss"]["pred"], names),
                   "noise prediction"))
    out.append(_section(7, "The U-Net predicts the noise", "Conditional 1-D U-Net with FiLM; "
                        "shapes from hooks on each block.", body))
    return "".join(out)


def _step_8(n: dict) -> str:
    lo, sm, names = n["loss"], n["sampling"], n["meta"]["joint_names"]
    sq = np.asarray(lo["squared_errors"])
    body = (f'<div class="box mono">L = mean over {sq.size} = {sq.shape[0]}×{sq.shape[1]} of '
            f"(ε − ε<sub>θ</sub>)² = <b>{lo['mse']:.6f}</b></div>"
            f"<p class=mono>first 6 squared errors: {_vec(sq.flatten()[:6].tolist(), 4)}</p>"
            + _table(["joint"] + [html.escape(x) for x in names],
                     [["MSE per joint"] + [_f(v, 4) for v in lo["per_joint"]]])
            + f"<p>This is the value <code>policy.forward(batch)</code> returned for this batch "
              f"with this ε and k, in {html.escape(lo['mode'])} mode"
            + (", padded rows masked out" if lo["masked"] else
               " (do_mask_loss_for_padding is off: padded rows count)") + ".</p>")
    start, end = sm["executed"]
    body += (f"<h3>At inference: {html.escape(sm['scheduler'])}, {sm['num_inference_steps']} "
             f"steps</h3><p>From Gaussian noise, the U-Net is called at steps "
             f"{sm['timesteps']}; each call's prediction moves the chunk toward a clean one. "
             f"Rows {start}..{end - 1} are what the robot executes before it replans.</p>")
    body += _img(plots.denoise_steps_figure(sm["samples_normalised"], sm["timesteps"], names),
                 "denoising steps")
    body += _img(plots.final_chunk_figure(sm["samples"][-1], sm["ground_truth"],
                                          n["actions"]["is_pad"], sm["executed"], names),
                 "sampled chunk")
    rmse = sm["rmse_executed"]
    rows = [["RMSE vs recorded, executed rows"] + ([_f(v, 2) for v in rmse] if rmse else
                                                  ["—"] * len(names)),
            ["roughness of the sampled chunk"] + [_f(v, 2) for v in sm["roughness_sample"]],
            ["roughness of the recorded chunk"] + [_f(v, 2)
                                                   for v in sm["roughness_ground_truth"]]]
    body += _table(["(LeRobot units)"] + [html.escape(x) for x in names], rows)
    body += ('<p class="sub">Roughness: RMS of the second difference along the chunk '
             "(jitter); a chunk much rougher than the recording is still noisy.</p>")
    return _section(8, "The loss, and sampling a chunk", "MSE between the actual and the "
                    "predicted noise; then DDIM denoising from pure noise.", body)


def _glance(n: dict) -> str:
    """The debugging questions first: is the loss low, do keypoints localise, is the chunk
    close to the demonstration and smooth?"""
    e, sm = n["encoder"], n["sampling"]
    grid, peak = e["feature_grid"], e.get("attention_peak")
    rmse, rough, rough_gt = sm["rmse_executed"], sm["roughness_sample"], sm[
        "roughness_ground_truth"]
    items = [f"loss at k = {n['noise']['k']}: <b>{n['loss']['mse']:.4f}</b>",
             f"keypoints: a {grid[0]}×{grid[1]} feature map" + (
                 f", mean peak attention {peak:.2f} (uniform {e['attention_uniform']:.2f})"
                 if peak is not None else "")]
    if rmse:
        items.append(f"sampled chunk vs recorded actions, executed rows: RMSE "
                     f"{min(rmse):.2f}–{max(rmse):.2f} per joint (LeRobot units)")
    items.append(f"roughness of the sampled chunk {min(rough):.2f}–{max(rough):.2f} "
                 f"(recorded {min(rough_gt):.2f}–{max(rough_gt):.2f})")
    return ('<div class="box"><b>At a glance.</b> ' + "; ".join(items) + ".</div>")


def render_page(numbers: dict[str, Any], images: dict[str, np.ndarray]) -> str:
    """The whole page as one HTML string (no external files or network)."""
    title = (f"explain: {numbers['meta']['policy']['name']} — episode "
             f"{numbers['meta']['episode']}, frame {numbers['meta']['frame']}")
    warn = ""
    if numbers["meta"]["policy"]["source"] != "checkpoint":
        warn = ('<div class="warn">This policy is untrained: its keypoints and noise '
                "predictions are random. Pass <code>--policy CHECKPOINT</code> to see a trained "
                "one.</div>")
    body = (_header(numbers) + warn + _glance(numbers) + _steps_1_to_3(numbers, images)
            + _step_4(numbers, images)
            + _steps_5_to_7(numbers) + _step_8(numbers))
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>'
            f"{html.escape(title)}</title><style>{CSS}</style></head><body><main>{body}"
            "</main></body></html>\n")
