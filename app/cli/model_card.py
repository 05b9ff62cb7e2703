"""The model card (MODEL_CARD.md) of a training run, written from its training.json, so the
two cannot drift; later runs on the same weights (`--init`) add their own sections."""

from __future__ import annotations

import json


def model_card(report: dict) -> str:
    """Markdown model card from the training report (config, data, time, validation)."""
    cfg = report["config"]
    lines = [
        "# volumesh depth enhancer weights",
        "",
        "Trained in-house by `volumesh train`'s stages (how they were run: below); no "
        "pretrained weights were used.",
        "",
        f"- configuration: `{cfg['name']}`, seed {report['seed']}, device `{report['device']}`",
        *([f"- {report['note']}"] if report.get("note") else []),
        f"- training meshes: {', '.join(report['data']['train'])}",
        f"- validation meshes (held apart by mesh): {', '.join(report['data']['validation'])}",
        "- never trained on: stanford-bunny (the benchmark's test model)",
        *_pairs_lines(report),
        *_selector_lines(report),
        *_gain_lines(report),
        "- the depth networks' copies shipped in `pipeline/enhance/weights` are stored as "
        "float16 and load as float32; mesh-level figures: README, Enhancement "
        "(`benchmarks/enhance.py`)",
        "",
        "| stage | steps | training time (min) | final loss |",
        "| --- | --- | --- | --- |",
    ]
    for stage in ("regressor", "vae", "ldm", "finetune"):
        if stage in report:
            r = report[stage]
            loss = r["final_loss"]
            lines.append(
                f"| {stage} | {r['steps']} | {r['train_seconds'] / 60:.1f} | "
                f"{loss if loss is None else round(loss, 4)} |"
            )
    lines += [
        "",
        "Validation (held-apart meshes; depth RMSE in thousandths of the view's depth range,",
        "about 1.6 mm per unit on a 1 m model; `edge` = 3-pixel band at depth edges):",
        "",
        "| stage | method | RMSE | edge RMSE |",
        "| --- | --- | --- | --- |",
    ]
    for stage in ("regressor", "vae", "ldm", "finetune"):
        for method, fig in report.get(stage, {}).get("validation", {}).items():
            if isinstance(fig, dict):
                lines.append(
                    f"| {stage} | {method} | {fig['rmse_permille']:.3f} | "
                    f"{fig['edge_rmse_permille']:.3f} |"
                )
    remasked = report.get("remasked")
    lines += _continuation_lines(report.get("continued"), "refined" in report,
                                 remasked is not None)
    lines += _refined_lines(report.get("refined"), remasked is not None)
    lines += _remasked_lines(remasked, "rebased" in report)
    lines += _rebased_lines(report.get("rebased"), "averaged" in report)
    lines += _averaged_lines(report.get("averaged"))
    lines += ["", "Config (of the first run above):", "", "```json", json.dumps(cfg, indent=1),
              "```", ""]
    return "\n".join(lines)


def _pairs_lines(report: dict) -> list[str]:
    """The card's lines on the depth networks' data (absent from a selector-only run)."""
    cfg = report["config"]
    if "train_pairs" not in report["data"]:
        return []
    return [
        f"- pairs: {report['data']['train_pairs']} training, "
        f"{report['data']['validation_pairs']} validation, "
        f"{cfg['data']['resolution']}² normalised depth (per view, relative to the bounding "
        "sphere); degradations: vertex noise along normals (amplitude "
        f"{cfg['data']['noise_fraction'][0]}–{cfg['data']['noise_fraction'][1]} of the largest "
        "extent, or below the lower bound for a share "
        f"{cfg['data'].get('light_noise_probability', 0)} of the poses), Azure-Kinect-like "
        "axial noise and flying pixels, holes, 4x "
        "down-then-up sampling; synthetic colour (albedo patches shaded by the clean normals) on "
        f"a share {cfg['data'].get('color_probability', 0)} of the poses, its Canny edges an input",
        f"- crops {cfg['crop']}², batch {cfg['batch']}, AdamW, warm-up + cosine schedule",
        "- source meshes are remeshed isotropically by the pipeline's remesh stage (edge "
        f"{cfg['data']['edge_fraction'][0]}–{cfg['data']['edge_fraction'][1]} of the largest "
        "extent) before the noise, as the enhance stage receives them",
        f"- the networks correct the render of the noisy mesh after {_presmoothing(cfg['data'])}, "
        "reading the noisy mesh's own render beside it (its offset from the smoothed one)",
        "- stages: the regressor (the plain baseline); the VAE; U-Net + ControlNet "
        "(v-prediction); then end-to-end fine-tuning of VAE, U-Net and ControlNet through the "
        f"unrolled {'/'.join(map(str, cfg['finetune_steps']))}-step DDIM sampler at strength "
        f"{cfg['finetune_strength']} on the decoded depth error",
    ]


def _selector_lines(report: dict) -> list[str]:
    """The card's lines on the twicing selector (the networks' pre-smoothing)."""
    if "selector" not in report:
        return []
    r, c = report["selector"], report["config"]["selector"]
    lines = [
        "- **selector** (`selector.safetensors`, `models/twicing_selector.py`): a per-vertex "
        f"MLP ({c['model']['hidden']} wide) weighing twicings at "
        f"{'/'.join(map(str, c['model']['iterations']))} iterations; it is the enhance stage's "
        "pre-smoothing and `--method selector`. Trained on "
        f"{r['draws']} noisy draws of the training meshes ({r['vertices']} vertices; edges "
        f"{c['edge_fraction'][0]}–{c['edge_fraction'][1]} of the largest extent, uniform noise "
        f"along normals of {c['noise_to_edge'][0]}–{c['noise_to_edge'][1]} edge lengths) for "
        f"{r['steps']} steps ({r['train_seconds'] / 60:.1f} min, data "
        f"{r['data_seconds'] / 60:.1f} min), loss: the blend's squared distance to the truth.",
        *([f"  Run as `{r['command']}` on {r['device']}, training meshes "
           f"{', '.join(r['data']['train'])}."] if "command" in r else []),
        "",
        "  Held-out meshes, one draw each, RMS distance to the truth in thousandths of the "
        "extent:",
        "",
        "  | mesh | noisy | best single count | adaptive twicing | selector |",
        "  | --- | --- | --- | --- | --- |",
    ]
    for name, f in r["validation"].items():
        lines.append(f"  | {name} | {f['noisy']:.3f} | {f['best_count']:.3f} | "
                     f"{f['adaptive_twicing']:.3f} | {f['selector']:.3f} |")
    return lines + [""] + _ensemble_lines(report)


def _ensemble_lines(report: dict) -> list[str]:
    """The card's lines on the shipped selector ensemble, where the selector is one."""
    if "selector_ensemble" not in report:
        return []
    e = report["selector_ensemble"]
    members = "; ".join(m.get("command", m.get("source", "")) for m in e["members"])
    c2m = e["protocol_c2m_rms_mm"]
    rows = [f"  | {mesh} | " + " | ".join("–" if v is None else f"{v:.4f}" for v in values) + " |"
            for mesh, values in c2m["selector_alone"].items()]
    return [
        f"  The shipped selector is an ensemble of {len(e['members'])} such runs (the mean of "
        f"their blend weights), made by `{e['command']}`; members: {members}. {e['note']}.",
        "",
        f"  Selector alone, C2M RMS mm, {c2m['benchmark']}:",
        "",
        "  | mesh | " + " | ".join(f"seed {m.get('seed', '?')}" for m in e["members"])
        + " | ensemble |",
        "  | --- |" + " --- |" * (len(e["members"]) + 1),
        *rows,
        "",
    ]


def _gain_lines(report: dict) -> list[str]:
    """The card's lines on the vertex gain networks (how far the mesh update follows)."""
    if "gain" not in report:
        return []
    r = report["gain"]
    c = r["config"]  # its own: the gain stage may run on weights another run trained
    methods = list(r["methods"])
    steps = ", ".join(f"{m} {log['steps']} steps ({log['train_seconds'] / 60:.1f} min)"
                      for m, log in r["methods"].items())
    lines = [
        "- **vertex gains** (" + ", ".join(f"`{m}_gain.safetensors`" for m in methods)
        + ", `models/vertex_gain.py`): per-vertex MLPs "
        f"({c['model']['hidden']} wide) from the views' steps (their mean along the normal, "
        "its spread over the views, the views' weight and the share of them that see it, per "
        "view) to the share of the "
        f"network's correction the vertex follows, in (0, {c['model']['max_gain']}). Trained on "
        f"{r['draws']} noisy draws of {', '.join(r['meshes'])} ({r['vertices']} seen vertices; "
        f"edges {c['edge_fraction'][0]}–{c['edge_fraction'][1]} of the largest extent, uniform "
        f"noise along normals of {c['noise_to_edge'][0]}–{c['noise_to_edge'][1]} edge lengths; "
        f"{c['views']} views at {c['resolution']}²), pre-smoothed and enhanced by the weights "
        f"above; {steps}, data {r['data_seconds'] / 60:.1f} min; loss: the moved vertex's "
        "squared distance to the truth along its normal.",
        *([f"  Run as `{r['command']}` on {r['device']}. The enhance stage uses them by "
           "default (`EnhanceConfig.learned_gain`)."] if "command" in r else []),
        "",
        "  Held-out meshes, one draw each, RMS distance to the truth in thousandths of the "
        "extent (no light remesh):",
        "",
        "  | mesh | pre-smoothed | " + " | ".join(
            f"{m}, fixed gain | {m}, learned gains" for m in methods) + " |",
        "  | --- | --- | " + " | ".join("--- | ---" for _ in methods) + " |",
    ]
    for name, f in r["validation"].items():
        cells = " | ".join(f"{f[f'{m}_fixed_gain']:.3f} | {f[f'{m}_learned_gain']:.3f}"
                           for m in methods)
        lines.append(f"  | {name} | {f['presmoothed']:.3f} | {cells} |")
    return lines + [""]


def _presmoothing(data: dict) -> str:
    iterations, passes = data.get("presmooth_iterations", 0), data.get("presmooth_passes", 1)
    if data.get("presmooth_learned") and iterations > 0:
        blend = "the shipped selector's per-vertex blend of twicings (`selector_presmoothed`)"
        if data.get("presmooth_bounded"):
            blend += ", then the bounded-noise refinement (`bounded_noise_refine`)"
        return blend
    if data.get("presmooth_adaptive"):
        return (f"twicing ({passes} passes) with its count chosen per vertex among several, "
                f"a pilot at {iterations} iterations estimating each count's bias")
    if passes == 1:
        return f"{iterations} Laplacian smoothing iterations (λ 0.5)"
    return (f"{iterations} Laplacian smoothing iterations (λ 0.5) in {passes} passes "
            "(twicing: each pass smooths what the passes before left and adds it back)")


def _continuation_lines(
    continued: dict | None, refined: bool = False, superseded: bool = False
) -> list[str]:
    """The card's section on a later fine-tuning of these weights (`volumesh train --init`);
    `refined`: the LDM was trained again after it (`_refined_lines`); `superseded`: all of
    them were (`_remasked_lines`)."""
    if not continued:
        return []
    shipped = ("superseded: the last section's are shipped" if superseded
               else "the shipped regressor; the vae and ldm were trained again, next section"
               if refined else "these are the shipped weights")
    lines = [
        "",
        f"## Fine-tuned since ({shipped})",
        "",
        f"- {continued['note']}",
        f"- the networks now correct the render after {_presmoothing(continued['data'])}; "
        "what the enhance stage feeds them: `EnhanceConfig.presmooth_*`",
        *([f"- {continued['inference_note']}"] if continued.get("inference_note") else []),
        f"- pairs: {continued['train_pairs']} training, {continued['validation_pairs']} "
        "validation, same meshes and split as above",
        *_stage_table(continued),
    ]
    lines += ["", "Validation on the new pre-smoothing, before and after (as above):", "",
              "| stage | method | RMSE before | RMSE after | edge before | edge after |",
              "| --- | --- | --- | --- | --- | --- |"]
    for stage in ("regressor", "finetune"):
        before, after = continued[stage]["validation_before"], continued[stage]["validation"]
        for method, fig in after.items():
            if isinstance(fig, dict):
                b = before[method]
                lines.append(
                    f"| {stage} | {method} | {b['rmse_permille']:.3f} | "
                    f"{fig['rmse_permille']:.3f} | {b['edge_rmse_permille']:.3f} | "
                    f"{fig['edge_rmse_permille']:.3f} |"
                )
    return lines


def _refined_lines(refined: dict | None, superseded: bool = False) -> list[str]:
    """The card's section on re-training the LDM to refine the regressor (`LDMModels.refines`):
    the report of a `--init ... --stages finetune` run, with its command."""
    if not refined:
        return []
    f, data = refined["finetune"], refined["data"]
    v = f["validation"]
    shipped = ("superseded: the next section's are shipped" if superseded
               else "these are the shipped vae and ldm")
    lines = [
        "",
        f"## The LDM refines the regressor ({shipped})",
        "",
        "- `ldm.safetensors` carries the regressor it refines (its `refines.*` tensors are the "
        "shipped `regressor.safetensors`, its config in the metadata): the LDM encodes, denoises "
        "and decodes around the regressor's estimate instead of the pre-smoothed base "
        "(`LDMModels.refines`, `TrainConfig.ldm_refines_regressor`; the split of CorrDiff, "
        "Mardani et al. 2023). The regressor stays frozen; the VAE, U-Net and ControlNet learn "
        "what it leaves.",
        f"- run as `{refined['command']}` on {refined['device']}, from the weights above: "
        f"{f['steps']} end-to-end steps in {f['train_seconds'] / 60:.1f} minutes, final loss "
        f"{f['final_loss']:.4f}; pairs in {data['seconds'] / 60:.1f} minutes",
        f"- pairs: {data['train_pairs']} training, {data['validation_pairs']} validation, same "
        f"meshes and split as above, the base depth after {_presmoothing(refined['config_data'])}"
        ", as the enhance stage now feeds the networks",
        "",
        f"Validation, {v['views']} held-apart renders (as above; `regressor`: the embedded "
        "regressor alone):",
        "",
        "| method | RMSE | edge RMSE |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {k} | {x['rmse_permille']:.3f} | {x['edge_rmse_permille']:.3f} |"
              for k, x in v.items() if isinstance(x, dict)]
    return lines + ["", refined["note"]]


def _remasked_lines(remasked: dict | None, superseded: bool = False) -> list[str]:
    """The card's section on the regressor and LDM trained again on the enhance stage's own
    degradation with the tight loss mask: the report of a `--init ... --stages
    regressor,finetune --mix mesh --loss-mask ...` run, with its command; `superseded`: a
    later section's networks are shipped (`_rebased_lines`)."""
    if not remasked:
        return []
    data = remasked["data"]
    shipped = ("superseded: the next section's are shipped" if superseded
               else "these are the shipped regressor, vae and ldm")
    lines = [
        "",
        f"## Trained again on mesh degradations with the tight loss mask ({shipped})",
        "",
        f"- run as `{remasked['command']}` on {remasked['device']}, from the weights above; "
        f"pairs in {data['seconds'] / 60:.1f} minutes: {data['train_pairs']} training, "
        f"{data['validation_pairs']} validation, same meshes and split as above, the base depth "
        f"after {_presmoothing(remasked['config_data'])}",
        "- the mix: only what a mesh's renders carry (vertex noise along normals, near-clean "
        "surfaces, colour); no sensor noise, holes or resampling, which never reach the enhance "
        "stage",
        f"- the loss leaves out pixels where an input is more than "
        f"{remasked['loss_mask_threshold_n']} (normalised depth) from the clean render "
        "(`TrainConfig.loss_mask_threshold_n`; 0.05 above): at 0.05 a few pixels where an input "
        "sees another surface carried about 40 % of the squared loss",
        *([f"- {remasked['note']}"] if remasked.get("note") else []),
        *_stage_table(remasked),
    ]
    v = remasked["finetune"]["validation"]
    lines += [
        "",
        f"Validation, {v['views']} held-apart renders of the same mix (thousandths of the depth "
        "range; `bulk`: without the pixels the tight mask leaves out; `normal`: along the "
        "normals as the mesh update weighs them; `regressor`: the new regressor alone):",
        "",
        "| method | RMSE | edge RMSE | normal RMSE | bulk RMSE | bulk normal RMSE |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    lines += [f"| {k} | {x['rmse_permille']:.3f} | {x['edge_rmse_permille']:.3f} | "
              f"{x['normal_rmse_permille']:.3f} | {x['bulk_rmse_permille']:.3f} | "
              f"{x['bulk_normal_rmse_permille']:.3f} |"
              for k, x in v.items() if isinstance(x, dict)]
    return lines


def _rebased_lines(rebased: dict | None, superseded: bool = False) -> list[str]:
    """The card's section on the regressor, LDM and vertex gains trained again on pairs whose
    base ends with the bounded-noise refinement (a `--init ... --stages
    regressor,finetune,gain` run), with its command; `superseded`: the next section's
    networks are shipped (`_averaged_lines`)."""
    if not rebased:
        return []
    data, r, f, g = rebased["data"], rebased["regressor"], rebased["finetune"], rebased["gain"]
    v = rebased["validation"]
    shipped = ("superseded: the next section's are shipped" if superseded
               else "these are the shipped regressor, vae, ldm and vertex gains")
    lines = [
        "",
        f"## Trained again on the bounded-noise refinement's base (seventeenth session; "
        f"{shipped})",
        "",
        f"- run as `{rebased['command']}` on {rebased['device']}, from the weights of the last "
        f"section; pairs in {data['minutes']} minutes: {data['train_pairs']} training, "
        f"{data['validation_pairs']} validation, same meshes and split as above",
        f"- recorded {rebased['recorded']}",
        "- the base depth is now the shipped selector's blend of twicings **ended by the "
        "bounded-noise refinement** (`bounded_noise_refine`, `DataConfig.presmooth_bounded`), "
        "as the enhance stage's pre-smoothing now is: each vertex moved along its normal by the "
        "middle of the range of the noisy vertices' offsets within three rings, where those "
        "offsets are light-tailed (README, Enhancement)",
        f"- the regressor stage ran {r['steps']} steps in its {r['cap_minutes']}-minute cap "
        f"(final loss {r['final_loss']}), the end-to-end finetune {f['steps']} steps in "
        f"{f['train_minutes']} minutes ({f['final_loss']}); the vertex gains then {g['steps']} "
        f"steps each on {g['draws']} draws of the seven real training meshes (data "
        f"{g['data_minutes']} minutes); the depth networks stored as float16",
        f"- validation, {v['views']} held-apart renders of the mesh mix (thousandths of the "
        "depth range, as in the last section; the base is the new one, so the rows are not "
        "comparable with the last section's):",
        *_bulk_table(v),
    ]
    return lines + ["", f"  {rebased['validation_note']}", f"- mesh level, {rebased['mesh_level']}"]


def _bulk_table(validation: dict) -> list[str]:
    """The depth-level validation table with the bulk columns (the tight loss mask's runs)."""
    return ["", "| method | RMSE | edge RMSE | bulk RMSE | bulk normal RMSE |",
            "| --- | --- | --- | --- | --- |",
            *[f"| {k} | {x['rmse_permille']:.3f} | {x['edge_rmse_permille']:.3f} | "
              f"{x['bulk_rmse_permille']:.3f} | {x['bulk_normal_rmse_permille']:.3f} |"
              for k, x in validation.items() if isinstance(x, dict)]]


def _averaged_lines(averaged: dict | None) -> list[str]:
    """The card's section on the regressor, LDM and vertex gains trained again on pairs whose
    refinement starts from the selector's averaged weights: the report of a `--init ...
    --stages regressor,finetune,gain` run (its training.json, less the loss logs), with its
    command, and how the shipped networks were made from it (`interpolate-weights`)."""
    if not averaged:
        return []
    data, g = averaged["data"], averaged["gain"]
    v = averaged["finetune"]["validation"]
    lines = [
        "",
        "## Trained again on the refinement from the selector's averaged weights, then "
        "interpolated with the last section's (twenty-third session; the shipped regressor, vae, "
        "ldm and vertex gains)",
        "",
        f"- shipped: {averaged['shipped']}",
        f"- run as `{averaged['command']}` on {averaged['device']}, from the weights of the "
        f"last section; pairs in {data['seconds'] / 60:.1f} minutes: {data['train_pairs']} "
        f"training, {data['validation_pairs']} validation, same meshes and split as above",
        "- the base depth is the shipped selector's blend of twicings ended by the bounded-noise "
        "refinement, which now starts from the blend of the selector's weights averaged over "
        "each vertex's neighbours (`BoundedNoiseConfig.weight_passes`), as the enhance stage "
        "makes it since the twenty-second session",
        f"- the vertex gains then {g['methods']['ldm']['steps']} steps each on {g['draws']} "
        f"draws of the seven real training meshes (data {g['data_seconds'] / 60:.1f} minutes); "
        "the depth networks stored as float16",
        *_stage_table(averaged),
        "",
        f"Validation of the run's own networks, {v['views']} held-apart renders of the mesh "
        "mix (thousandths of the depth range, as in the last section; the base is the new "
        "one):",
        *_bulk_table(v),
    ]
    lines += ["", "Vertex gains, held-out meshes, one draw each, RMS distance to the truth in "
              "thousandths of the extent (no light remesh):", "",
              "| mesh | pre-smoothed | ldm, fixed gain | ldm, learned gains | regressor, fixed "
              "gain | regressor, learned gains |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {m} | {x['presmoothed']:.3f} | {x['ldm_fixed_gain']:.3f} | "
              f"{x['ldm_learned_gain']:.3f} | {x['regressor_fixed_gain']:.3f} | "
              f"{x['regressor_learned_gain']:.3f} |" for m, x in g["validation"].items()]
    return lines + ["", f"- mesh level, {averaged['mesh_level']}"]


def _stage_table(run: dict) -> list[str]:
    """The steps, peak learning rate, time and final loss of a later run's two stages."""
    lines = ["", "| stage | steps | peak lr | training time (min) | final loss |",
             "| --- | --- | --- | --- | --- |"]
    for stage in ("regressor", "finetune"):
        r = run[stage]
        lines.append(f"| {stage} | {r['steps']} | {r['lr']} | {r['train_seconds'] / 60:.1f} | "
                     f"{round(r['final_loss'], 4)} |")
    return lines
