//! The training loop of `usplat4d optimize`: load the model (less the Gaussians that
//! key-node selection culled), resume from a checkpoint when one of the same run exists,
//! then per step draw the batch frames, take L_rgb ([`super::step`]) plus the recipe's
//! graph or motion terms, tie static poses, update every Adam group, run density control
//! on its schedule, log, and checkpoint. Writes the trained model directory, its
//! `training_log.parquet`, and with the usplat4d recipe the roles (`key_nodes.parquet`) and
//! graph (`edges.parquet`) of the trained Gaussians.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use super::adam::{Adam, Group};
use super::checkpoint::{self, Checkpoint};
use super::density::{self, DensityStats};
use super::graph_loss::GraphObjective;
use super::image_loss::ImageLossWeights;
use super::nonkey_weights::{self, NonkeyWeights};
use super::objective::{GraphSource, KnnMotion, OriginAnchors, build_graph, trained_graph};
use super::params::{OptimizeParams, OptimizeSettings, Recipe};
use super::poses::PoseGrads;
use super::state::{StateGrads, TrainState};
use super::step::{TrainingViews, image_step};
use super::timing::PhaseTimes;
use crate::context::Context;
use crate::model::{Model, SH_FRAME_KEY};
use crate::render::RenderSettings;
use crate::scene::Scene;
use crate::tables::edges::Edges;
use crate::tables::key_nodes::{KeyNodes, Role};
use crate::tables::training_log::{LR_GROUPS, LogRow};
use crate::tables::{self, Provenance, Table};
use crate::util::rng::{Rng, mix};

/// The phase in which L_rgb and the motion or graph terms run side by side.
const BESIDE: &str = "L_rgb beside the motion terms";

/// The frames of step `step`: positions `step·B .. step·B + B` of an endless stream made of
/// one seeded permutation of 0..T per epoch (the release's `infinite_batches`). A pure
/// function of (seed, step), so a resumed run draws the same frames.
pub fn batch_frames(seed: u64, step: u32, frames: usize, batch: usize) -> Vec<usize> {
    let start = step as usize * batch;
    let mut perm: Option<(usize, Vec<usize>)> = None;
    (start..start + batch)
        .map(|k| {
            let epoch = k / frames;
            if perm.as_ref().is_none_or(|(e, _)| *e != epoch) {
                let mut rng = Rng::new(mix(seed) ^ mix(epoch as u64 ^ 0xba7c_4000_0000));
                let mut p: Vec<usize> = (0..frames).collect();
                for i in (1..frames).rev() {
                    p.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
                }
                perm = Some((epoch, p));
            }
            perm.as_ref().map(|(_, p)| p[k % frames]).unwrap_or(0)
        })
        .collect()
}

/// The graph inputs of the usplat4d recipe.
struct GraphInputs {
    keys: KeyNodes,
    edges: Edges,
    /// The edges table's graph metadata (kept in the learned table) and the λ / unit² of its
    /// non-key weights, if it has them.
    metadata: Option<String>,
    nonkey_lambda: Option<f64>,
}

fn read_graph(p: &OptimizeParams, s: &OptimizeSettings) -> anyhow::Result<Option<GraphInputs>> {
    let (Some(kn), Some(ed)) = (&p.keynodes, &p.edges) else { return Ok(None) };
    let keys = tables::key_nodes::read(&kn.join(tables::key_nodes::KeyNodesTable::file_name()))?;
    let path = ed.join(tables::edges::EdgesTable::file_name());
    let edges = tables::edges::read(&path)?;
    let meta = tables::io::TableReader::open::<tables::edges::EdgesTable>(&path)?
        .metadata_value(crate::stages::edges::GRAPH_KEY);
    let nonkey_lambda = meta.as_deref().map(nonkey_weights::lambda_from_graph_metadata);
    let nonkey_lambda = match (nonkey_lambda, s.graph.nonkey_weights) {
        (Some(Ok(l)), _) => Some(l),
        (_, NonkeyWeights::Table) => None,
        (None, NonkeyWeights::Current) => anyhow::bail!(
            "{}: no '{}' metadata (non-key weight sharpness and distance unit), which \
             --nonkey-weights current needs; write the table with `usplat4d edges`",
            path.display(),
            crate::stages::edges::GRAPH_KEY
        ),
        (Some(Err(e)), NonkeyWeights::Current) => anyhow::bail!("{}: {e}", path.display()),
    };
    Ok(Some(GraphInputs { keys, edges, metadata: meta, nonkey_lambda }))
}

/// The recipe's non-image terms.
enum Objective {
    Knn(KnnMotion),
    Graph(Box<GraphObjective>),
}

/// The recipe's objective for `state`: the graph objective from `graph`'s source and
/// anchors on `learned` edges (the input's by default), or without a graph the kNN graph.
fn build_objective(
    s: &OptimizeSettings,
    graph: Option<(&GraphSource, OriginAnchors)>,
    state: &TrainState,
    learned: Option<&Edges>,
) -> anyhow::Result<Objective> {
    Ok(match graph {
        None => Objective::Knn(KnnMotion::new(state, s.knn_k)),
        Some((src, anchors)) => Objective::Graph(Box::new(build_graph(
            src,
            state,
            learned.unwrap_or(&src.edges),
            anchors,
            &s.graph,
        )?)),
    })
}

/// One Adam group per trainable tensor of the graph objective, after the image groups.
fn add_graph_groups(adam: &mut Adam, o: &mut GraphObjective, s: &OptimizeSettings) {
    for slice in o.params_mut() {
        let lr = if slice.lr_key == "dists_key" { s.lr.lr_lengths } else { s.lr.lr_graph };
        adam.groups.push(Group {
            name: slice.name.to_string(),
            lr,
            m: vec![0.0; slice.values.len()],
            v: vec![0.0; slice.values.len()],
        });
    }
}

/// Restore the graph objective's tensors from a checkpoint.
fn restore_graph(o: &mut GraphObjective, saved: &[(String, Vec<f32>)]) -> anyhow::Result<()> {
    let slices = o.params_mut();
    if slices.len() != saved.len() {
        anyhow::bail!(
            "checkpoint: {} graph tensors, the objective has {}",
            saved.len(),
            slices.len()
        );
    }
    for (slice, (name, v)) in slices.into_iter().zip(saved) {
        if slice.name != name || slice.values.len() != v.len() {
            anyhow::bail!(
                "checkpoint: graph tensor {name} does not match the objective's {}",
                slice.name
            );
        }
        slice.values.copy_from_slice(v);
    }
    Ok(())
}

/// The training log's learning rates: image groups by name, graph tensors as `graph` and
/// `lengths`.
fn log_rates(adam: &Adam) -> Vec<(String, f32)> {
    let mut out: Vec<(String, f32)> = Vec::new();
    for g in &adam.groups {
        let name = match g.name.as_str() {
            "dists_key" => "lengths",
            n if LR_GROUPS.contains(&n) => n,
            _ => "graph",
        };
        if !out.iter().any(|(k, _)| k == name) {
            out.push((name.to_string(), g.lr));
        }
    }
    out
}

/// What the graph objective is built from, and the input model's p° and u for its first
/// build.
fn graph_source(
    p: &OptimizeParams,
    model: &Model,
    views: &TrainingViews,
    g: &GraphInputs,
) -> anyhow::Result<(GraphSource, OriginAnchors)> {
    let (nt, n) = (model.num_frames(), model.gaussians.len());
    let t_hat: HashMap<u32, usize> =
        g.keys.id.iter().zip(&g.keys.t_hat).map(|(&i, &t)| (i, t as usize)).collect();
    // the model rows whose rotation each frame gives (those with t̂ there)
    let mut at_frame: Vec<Vec<usize>> = vec![Vec::new(); nt];
    for (r, id) in model.gaussians.id.iter().enumerate() {
        if let Some(&t) = t_hat.get(id).filter(|&&t| t < nt) {
            at_frame[t].push(r);
        }
    }
    let mut p0 = Vec::with_capacity(nt * n);
    let mut q_hat = HashMap::with_capacity(t_hat.len());
    for (t, rows) in at_frame.iter().enumerate() {
        let f = model.frame(t)?;
        p0.extend(f.position);
        q_hat.extend(rows.iter().map(|&r| (model.gaussians.id[r], f.rotation[r])));
    }
    let dir = p
        .uncertainty
        .as_ref()
        .ok_or_else(|| anyhow::anyhow!("the usplat4d recipe needs --uncertainty DIR"))?;
    let reader = tables::uncertainty::UncertaintyReader::open(
        &dir.join(tables::uncertainty::UncertaintyTable::file_name()),
    )?;
    if reader.num_frames() != nt {
        anyhow::bail!("{}: {} frames, the model has {nt}", dir.display(), reader.num_frames());
    }
    let cols: Vec<Option<usize>> = {
        let at: HashMap<u32, usize> =
            reader.ids().iter().enumerate().map(|(k, &i)| (i, k)).collect();
        model.gaussians.id.iter().map(|i| at.get(i).copied()).collect()
    };
    let mut u = Vec::with_capacity(nt * n);
    for t in 0..nt {
        let f = reader.frame(t)?;
        u.extend(cols.iter().map(|c| c.map_or(1e8, |k| f.u[k])));
    }
    let rot_cw = (0..nt)
        .map(|t| {
            let w2c = views.training_camera(t).w2c.as_dmat4();
            glam::DMat3::from_mat4(w2c)
        })
        .collect();
    let source = GraphSource {
        keys: g.keys.clone(),
        edges: g.edges.clone(),
        q_hat,
        rot_cw,
        nonkey_lambda: g.nonkey_lambda,
    };
    Ok((source, OriginAnchors { origin: model.gaussians.id.clone(), p0, u }))
}

/// Input files whose bytes the checkpoint fingerprint covers.
fn input_files(p: &OptimizeParams) -> Vec<PathBuf> {
    let mut v = vec![
        Model::gaussians_path(&p.model),
        Model::trajectories_path(&p.model),
        Scene::cameras_path(&p.scene),
    ];
    if let Some(d) = &p.uncertainty {
        v.push(d.join(tables::uncertainty::UncertaintyTable::file_name()));
    }
    if let Some(d) = &p.keynodes {
        v.push(d.join(tables::key_nodes::KeyNodesTable::file_name()));
    }
    if let Some(d) = &p.edges {
        v.push(d.join(tables::edges::EdgesTable::file_name()));
    }
    v
}

/// Half the bounding-box diagonal of `p` `[N, 3]` (the scene extent of density control).
fn extent(p: &[[f32; 3]]) -> f32 {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for q in p {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    0.5 * (0..3).map(|k| (hi[k] - lo[k]).max(0.0).powi(2)).sum::<f32>().sqrt()
}

/// Adam over the image parameters of `state`, groups in [`density::group_layouts`] order.
fn new_adam(state: &TrainState, s: &OptimizeSettings) -> Adam {
    let (n, t) = (state.n(), state.frames());
    Adam::new(&[
        ("position", s.lr.lr_position, t * n * 3),
        ("rotation", s.lr.lr_rotation, t * n * 4),
        ("scale", s.lr.lr_scale, n * 3),
        ("opacity", s.lr.lr_opacity, n),
        ("color", s.lr.lr_color, n * 3),
        ("sh_rest", s.lr.lr_sh_rest, state.sh_rest.len()),
    ])
}

/// `usplat4d optimize`.
pub fn run(p: &OptimizeParams, ctx: &Context) -> anyhow::Result<()> {
    run_timed(p, ctx, false).map(|_| ())
}

/// [`run`], returning the wall time of each phase summed over the steps this run took
/// after its first (the first is warm-up), and its CPU time with `cpu_time`; and the wall
/// seconds of the graph initialisation before step 0 (0 when none ran).
pub fn run_timed(
    p: &OptimizeParams,
    ctx: &Context,
    cpu_time: bool,
) -> anyhow::Result<(PhaseTimes, f64)> {
    let _span = tracing::info_span!("optimize").entered();
    let s = p.settings()?;
    let model = Model::load(&p.model)?;
    let scene = Scene::load(&p.scene)?;
    let views = TrainingViews::new(&scene, &model)?;
    if views.len() != model.num_frames() {
        anyhow::bail!(
            "{}: {} training frames, but the model {} has {}",
            p.scene.display(),
            views.len(),
            p.model.display(),
            model.num_frames()
        );
    }
    let graph = match s.recipe {
        Recipe::Usplat4d => read_graph(p, &s)?,
        Recipe::Vanilla => None,
    };
    let role: HashMap<u32, Role> = graph
        .as_ref()
        .map(|g| g.keys.id.iter().copied().zip(g.keys.role.iter().copied()).collect())
        .unwrap_or_default();
    // Gaussians culled by key-node selection leave the model at the start (release row 35).
    let keep: Vec<bool> =
        model.gaussians.id.iter().map(|i| role.get(i) != Some(&Role::Culled)).collect();
    if !keep.contains(&true) {
        anyhow::bail!(
            "{}: key-node selection culled all {} Gaussians of {} (no key node was selected); \
             nothing is left to optimise",
            p.keynodes.as_deref().unwrap_or(std::path::Path::new("--keynodes")).display(),
            keep.len(),
            p.model.display()
        );
    }
    let scene_extent = extent(&model.frame(0)?.position);

    let mut settings_json = serde_json::to_value(&s)?;
    settings_json["checkpoint-every"] = serde_json::Value::Null;
    let fp = checkpoint::fingerprint(&settings_json, &input_files(p))?;
    let ckpt_path = checkpoint::path_of(&p.out);
    let resumed = checkpoint::load(&ckpt_path, &fp)?;
    let mut c = match resumed {
        Some(c) => {
            ctx.info(format!(
                "optimize: resuming after step {} from {}",
                c.step,
                ckpt_path.display()
            ));
            c
        }
        None => {
            let state = TrainState::from_model(&model, Some(&keep))?;
            let next_id = model.gaussians.id.iter().max().map_or(0, |m| m + 1);
            Checkpoint {
                step: 0,
                next_id,
                adam: new_adam(&state, &s),
                density: DensityStats::new(state.n()),
                state,
                graph: Vec::new(),
                log: Vec::new(),
            }
        }
    };
    let (source, anchors) = match &graph {
        Some(g) => graph_source(p, &model, &views, g).map(|(s, a)| (Some(s), Some(a)))?,
        None => (None, None),
    };
    let mut objective = build_objective(&s, source.as_ref().zip(anchors), &c.state, None)?;
    match &mut objective {
        Objective::Graph(o) if c.step == 0 => add_graph_groups(&mut c.adam, o, &s),
        Objective::Graph(o) => restore_graph(o, &c.graph)?,
        Objective::Knn(_) if c.step == 0 => {}
        Objective::Knn(k) => {
            *k = KnnMotion::from_tensors(&c.graph)
                .ok_or_else(|| anyhow::anyhow!("{}: no kNN graph", ckpt_path.display()))?;
        }
    }
    let mut init_seconds = 0.0;
    if let (Objective::Graph(o), 0) = (&mut objective, c.step) {
        let bar = ctx.progress(s.graph.init.max_iters as u64, "graph init");
        let started = Instant::now();
        let r = o.initialise(&mut c.state.poses, &s.graph.init, s.seed, &|what, k| {
            bar.set_message(what.to_string());
            bar.set_position(k as u64);
        });
        bar.finish_and_clear();
        init_seconds = started.elapsed().as_secs_f64();
        ctx.info(format!(
            "optimize: graph initialisation: non-key source poses {} iterations (loss {:.4}), \
             keys {} iterations (loss {:.4}), {:.1} s",
            r.nonkey_iters, r.nonkey_loss, r.key_iters, r.key_loss, init_seconds
        ));
    }
    let render = RenderSettings::default();
    views.preload(render.background)?;
    let renderer = crate::stages::device::renderer(ctx)?;
    let bar = ctx.progress(s.steps as u64, "optimize");
    bar.set_position(c.step as u64);
    let first_step = c.step;
    let mut times = PhaseTimes::default();
    let mut grads = StateGrads::zeros(&c.state, s.batch_frames);
    let mut poses_grad = PoseGrads::zeros(c.state.poses.frames, c.state.n());
    while c.step < s.steps {
        let step = c.step;
        let started = Instant::now();
        let mut timer = if cpu_time { PhaseTimes::with_cpu_time() } else { PhaseTimes::default() };
        let batch = batch_frames(s.seed, step, views.len(), s.batch_frames);
        // The track term acts on its schedule; a step that carries it may stay out of the
        // density statistics (the release's).
        let tracks_on = s.track.active(step, s.density.last_reset_before(step, s.steps));
        let weights =
            ImageLossWeights { track: if tracks_on { s.image.track } else { 0.0 }, ..s.image };
        // L_rgb (batch frames) and the motion or graph terms (all frames) are independent:
        // they run side by side, each into its own gradients, added in a fixed order.
        let beside = timer.start();
        let (mut t_img, mut t_motion) = (PhaseTimes::default(), PhaseTimes::default());
        let state = &c.state;
        let (img, extra) = rayon::join(
            || {
                image_step(
                    &renderer, state, &views, &batch, &weights, &render, &mut grads, &mut t_img,
                )
            },
            || {
                poses_grad.reset(state.poses.frames, state.n());
                match &mut objective {
                    Objective::Knn(k) => t_motion.time("kNN motion terms", || {
                        k.evaluate(&state.poses, s.vanilla_weights, &mut poses_grad)
                    }),
                    Objective::Graph(o) => o.evaluate(
                        &state.poses,
                        &batch,
                        mix(s.seed ^ step as u64),
                        &mut poses_grad,
                        &mut t_motion,
                    ),
                }
            },
        );
        let img = img?;
        timer.stop(BESIDE, beside);
        timer.merge_within(BESIDE, &t_img);
        timer.merge_within(BESIDE, &t_motion);
        timer.time("add image pose gradients", || poses_grad.add_rows(&grads.poses, &batch));
        let mut terms: Vec<(String, f64)> = Vec::new();
        terms.extend(img.terms.iter().map(|(k, v)| (k.to_string(), *v)));
        terms.extend(extra.iter().map(|(k, v)| (k.to_string(), *v)));
        let loss: f64 = terms.iter().map(|(_, v)| v).sum();
        timer.time("tie static poses", || c.state.tie_static(&mut poses_grad));
        let adam_started = timer.start();
        c.adam.begin_step();
        let st = &mut c.state;
        c.adam.update(0, st.poses.position.as_flattened_mut(), poses_grad.position.as_flattened());
        c.adam.update(1, st.poses.rotation.as_flattened_mut(), poses_grad.rotation.as_flattened());
        c.adam.update(2, st.log_scale.as_flattened_mut(), grads.log_scale.as_flattened());
        c.adam.update(3, &mut st.logit_opacity, &grads.logit_opacity);
        c.adam.update(4, st.color.as_flattened_mut(), grads.color.as_flattened());
        c.adam.update(5, &mut st.sh_rest, &grads.sh_rest);
        if let Objective::Graph(o) = &mut objective {
            for (k, slice) in o.params_mut().into_iter().enumerate() {
                c.adam.update(6 + k, slice.values, slice.grads);
            }
        }
        timer.stop("Adam", adam_started);
        let density_started = timer.start();
        let carries_tracks = img.terms.iter().any(|(k, _)| *k == "track");
        if s.track.density_stats || !carries_tracks {
            c.density.add(&img.screen_grad, &img.screen_count);
        }
        if s.density.active(step, s.steps) {
            let protected: Vec<bool> =
                c.state.ids.iter().map(|i| role.get(i) == Some(&Role::Key)).collect();
            // The objective's p° and u rows are in this order until it is rebuilt.
            let origin = c.state.origin.clone();
            let r = density::densify_and_prune(
                &mut c.state,
                &mut c.adam,
                &c.density,
                &protected,
                &s.density,
                scene_extent,
                s.seed,
                step,
                &mut c.next_id,
            );
            tracing::info!(step, ?r, n = c.state.n(), "density control");
            c.density = DensityStats::new(c.state.n());
            let (learned, graph) = match (&mut objective, &source) {
                (Objective::Graph(o), Some(src)) => {
                    let (p0, u) = o.take_anchors();
                    (Some(o.learned_edges()), Some((src, OriginAnchors { origin, p0, u })))
                }
                _ => (None, None),
            };
            let mut rebuilt = build_objective(&s, graph, &c.state, learned.as_ref())?;
            if let (Objective::Graph(new), Objective::Graph(old)) = (&mut rebuilt, &objective) {
                let origin: HashMap<u32, u32> =
                    c.state.ids.iter().copied().zip(c.state.origin.iter().copied()).collect();
                new.carry_over(old, |id| origin.get(&id).copied().unwrap_or(id));
            }
            objective = rebuilt;
            c.adam.groups.truncate(6);
            if let Objective::Graph(o) = &mut objective {
                add_graph_groups(&mut c.adam, o, &s);
            }
        }
        if s.density.reset(step, s.steps) {
            density::reset_opacity(&mut c.state, &mut c.adam);
        }
        timer.stop("density control", density_started);
        if step > first_step {
            times.merge(&timer);
        }
        c.log.push(LogRow {
            step,
            num_gaussians: c.state.n() as u32,
            seconds: started.elapsed().as_secs_f64(),
            loss,
            terms,
            lr: log_rates(&c.adam),
        });
        c.step += 1;
        bar.set_message(format!("loss {loss:.4}"));
        bar.inc(1);
        if s.checkpoint_every.is_some_and(|k| c.step.is_multiple_of(k)) && c.step < s.steps {
            c.graph = match &mut objective {
                Objective::Graph(o) => o
                    .params_mut()
                    .into_iter()
                    .map(|p| (p.name.to_string(), p.values.to_vec()))
                    .collect(),
                Objective::Knn(k) => k.to_tensors(),
            };
            checkpoint::save(&ckpt_path, &fp, &c)?;
            if p.abort_after_step == Some(c.step) {
                std::process::abort();
            }
        }
    }
    bar.finish_and_clear();
    let learned = match &objective {
        Objective::Graph(o) => Some(o.learned_edges()),
        Objective::Knn(_) => None,
    };
    write_outputs(p, &s, &model, &c, graph.as_ref().zip(learned.as_ref()))?;
    let dir = checkpoint::dir_of(&p.out);
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?;
    }
    Ok((times, init_seconds))
}

/// The trained model, the training log, and (usplat4d) the roles and graph of the trained
/// Gaussians: a new Gaussian is a non-key with its origin's t̂ and non-key edges. The model
/// keeps what the input model carries besides its Gaussians: its SH frame, its own training
/// cameras and the scene-to-model similarity (an imported base stays one).
fn write_outputs(
    p: &OptimizeParams,
    s: &OptimizeSettings,
    input: &Model,
    c: &Checkpoint,
    graph: Option<(&GraphInputs, &Edges)>,
) -> anyhow::Result<()> {
    let prov = Provenance::new("optimize", &serde_json::json!({ "params": p, "resolved": s }));
    let st = &c.state;
    Model::save(
        &p.out,
        &st.to_gaussians(),
        (0..st.frames()).map(|t| Ok(st.frame_state(t))),
        &prov.clone().with_metadata(SH_FRAME_KEY, input.sh_frame.name()),
    )?;
    if let (Some(cameras), Some(sim)) = (&input.cameras, &input.scene_to_model) {
        Model::save_cameras(&p.out, cameras, sim, &prov)?;
    }
    tables::training_log::write(
        &p.out.join(tables::training_log::TrainingLogTable::file_name()),
        &c.log,
        &prov,
    )?;
    if let Some((g, learned)) = graph {
        let (keys, _) = trained_graph(st, &g.keys, &g.edges);
        let edges = learned;
        tables::key_nodes::write(
            &p.out.join(tables::key_nodes::KeyNodesTable::file_name()),
            &keys,
            &prov,
        )?;
        let prov = match &g.metadata {
            Some(m) => prov.with_metadata(crate::stages::edges::GRAPH_KEY, m),
            None => prov,
        };
        tables::edges::write(&p.out.join(tables::edges::EdgesTable::file_name()), edges, &prov)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_cover_every_frame_once_per_epoch() {
        let t = 11;
        let frames: Vec<usize> = (0..11).flat_map(|s| batch_frames(3, s, t, 8)).collect();
        for epoch in frames.chunks(t).take(8) {
            let mut e = epoch.to_vec();
            e.sort_unstable();
            assert_eq!(e, (0..t).collect::<Vec<_>>());
        }
        assert_ne!(batch_frames(3, 0, t, 8), batch_frames(4, 0, t, 8), "seeded");
        assert_eq!(batch_frames(3, 5, t, 8), frames[40..48].to_vec(), "pure in (seed, step)");
    }
}
