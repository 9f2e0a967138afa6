//! The matrix of a benchmark profile: every (scene, method or sweep point, seed) as a fully
//! resolved run config with its hash, checked before any run starts.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context};
use sha2::{Digest, Sha256};
use sos_core::config::RunConfig;
use sos_datasets::layouts::Format;
use sos_datasets::synthetic::SyntheticConfig;
use toml::{Table, Value};

use super::overlay::{self, OverlayError};
use super::spec::{names, BenchFile, SweepMode, SweepSpec};

/// Where a run sits in a sweep.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct SweepCoord {
    /// The sweep's name.
    pub name: String,
    /// The point's label.
    pub label: String,
    /// Position of the point in the sweep.
    pub index: usize,
    /// The point's number when the sweep varies one numeric key (the plots' x axis).
    pub x: Option<f64>,
}

/// A synthetic scene to write in a dataset layout before the runs that read it.
#[derive(Debug, Clone)]
pub struct Generate {
    /// The layout.
    pub layout: Format,
    /// The scene.
    pub synthetic: SyntheticConfig,
    /// The spec as written (part of the run hash).
    pub spec: Table,
}

impl Generate {
    /// The folder a layout is written to, under the benchmark's output folder.
    pub fn dir(&self, out: &Path) -> PathBuf {
        out.join("scenes").join(format!(
            "{}-{}",
            self.layout.name(),
            &hash_text(&toml::to_string(&self.spec).unwrap_or_default())[..12]
        ))
    }
}

/// Who a run is in the matrix: what a planned run and its record share.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RunKey {
    /// `<scene>__<variant>__s<seed>`: the record's file name.
    pub id: String,
    /// Scene name.
    pub scene: String,
    /// Method name (for a sweep point: the method it varies).
    pub method: String,
    /// The row of the report: the method, or `<sweep>: <label>`.
    pub variant: String,
    /// The sweep point, if any.
    pub sweep: Option<SweepCoord>,
    /// The run's seed.
    pub seed: u64,
}

/// One run of the matrix.
#[derive(Debug, Clone)]
pub struct PlannedRun {
    /// Who it is.
    pub key: RunKey,
    /// The folder the config's relative paths resolve against.
    pub config_dir: PathBuf,
    /// A layout to write first.
    pub generate: Option<Generate>,
    /// The resolved config (without `name` and `output_dir`, which the runner sets).
    pub config: Value,
    /// Hash of everything that decides the run's result.
    pub hash: String,
    /// Hash of everything that decides its stage 1: runs with equal ones (sweep points that
    /// change only stage-2 settings) may share one stage 1.
    pub stage1_hash: String,
    /// What [`shard`] groups runs by: the stage-1 part of the config as the benchmark file
    /// writes it, before resolution, so every machine computes the same whatever it can run.
    pub shard_key: String,
    /// Why the run cannot happen here (missing data or weights, a kind not built in).
    pub skip: Option<String>,
    /// Another build that runs it with its own `sos train` (its config then in that build's keys).
    pub program: Option<PathBuf>,
    /// The id of this build's run whose stage-1 checkpoint `program` starts from (with its
    /// `sos segment`; the method's `stage1_of`): planned before it, in the same shard.
    pub stage1_of: Option<String>,
    /// Size of the view the run times with its mask (none: the scene's own).
    pub view_size: Option<[u32; 2]>,
}

/// The planned runs of a profile, sorted by id.
pub struct Matrix {
    /// The profile's name (`all` when the file has none).
    pub profile: String,
    /// Learning-curve samples per stage.
    pub curve_points: usize,
    /// Every run.
    pub runs: Vec<PlannedRun>,
}

/// Resolves the matrix of `profile` (the file's default profile when `None`). Every overlay
/// is applied and every resulting config parsed here, so a bad key path fails before any run.
pub fn plan(file: &BenchFile, profile: Option<&str>, out: &Path) -> anyhow::Result<Matrix> {
    let fpath = file.path.display().to_string();
    let profile_name = profile.map(str::to_owned).or_else(|| file.bench.default_profile.clone());
    let prof = match &profile_name {
        Some(p) => Some(
            file.profiles
                .get(p)
                .ok_or_else(|| anyhow!("{fpath}: no profile `{p}`; profiles: {}", names(file.profiles.keys())))?,
        ),
        None => None,
    };
    let scenes: Vec<String> =
        prof.and_then(|p| p.scenes.clone()).unwrap_or_else(|| file.scenes.keys().cloned().collect());
    let methods: Vec<String> =
        prof.and_then(|p| p.methods.clone()).unwrap_or_else(|| file.methods.keys().cloned().collect());
    let sweeps: Vec<&SweepSpec> = match prof {
        Some(p) => {
            p.sweeps.iter().map(|n| file.sweep.iter().find(|s| &s.name == n).expect("checked on load")).collect()
        }
        None => file.sweep.iter().collect(),
    };
    let seeds = prof.and_then(|p| p.seeds.clone()).unwrap_or_else(|| file.bench.seeds.clone());
    if seeds.is_empty() {
        bail!("{fpath}: no seeds to run");
    }
    let curve_points = prof.and_then(|p| p.curve_points).unwrap_or(file.bench.curve_points);
    let view_size = prof.and_then(|p| p.view_size).or(file.bench.view_size);
    let empty = Table::new();
    let profile_set = prof.map_or(&empty, |p| &p.set);

    let mut runs = Vec::new();
    for scene_name in &scenes {
        let scene = &file.scenes[scene_name];
        let base_path = file.dir().join(&scene.config);
        let base = RunConfig::load(&base_path).with_context(|| format!("{fpath}: scene `{scene_name}`"))?;
        let config_dir = base_path.parent().map(Path::to_path_buf).unwrap_or_default();
        let mut value = Value::try_from(overlay::resolve(base)).context("serialising a run config")?;
        let generate = scene
            .generate
            .as_ref()
            .map(|g| parse_generate(g).with_context(|| format!("{fpath}: scene `{scene_name}`, `generate`")))
            .transpose()?;
        let mut scene_skip = None;
        for (what, set) in [("scene", &scene.set), ("profile", profile_set)] {
            if let Err(e) = overlay::apply(&mut value, set) {
                match e {
                    OverlayError::Unregistered { .. } => scene_skip = Some(e.to_string()),
                    OverlayError::Path { .. } => bail!("{fpath}: scene `{scene_name}`, {what} overrides: {e}"),
                }
            }
        }
        if let Some(g) = &generate {
            let dir = g.layout.scene_dir(&g.dir(out));
            overlay::set(&mut value, "scene.path", Value::String(dir.display().to_string()))
                .with_context(|| format!("{fpath}: scene `{scene_name}`: a generated scene needs a `path` key"))?;
        }
        let context = RunContext {
            file,
            scene: scene_name,
            config_dir: &config_dir,
            generate: generate.as_ref(),
            skip: scene_skip,
            curve_points,
            view_size,
        };
        for method in &methods {
            let spec = &file.methods[method];
            if spec.scenes.as_ref().is_some_and(|s| !s.contains(scene_name)) {
                continue;
            }
            for seed in &seeds {
                if spec.program.is_some() {
                    runs.push(context.program_run(method, &value, *seed)?);
                    continue;
                }
                let points = vec![Point { label: String::new(), set: spec.set.clone(), x: None }];
                runs.extend(context.runs(&value, method, None, &points, *seed)?);
            }
        }
        for sweep in &sweeps {
            if sweep.scenes.as_ref().is_some_and(|s| !s.contains(scene_name)) {
                continue;
            }
            let method = sweep.method.clone().unwrap_or_else(|| file.bench.baseline.clone());
            let mut with_method = value.clone();
            overlay::apply(&mut with_method, &file.methods[&method].set)
                .with_context(|| format!("{fpath}: method `{method}`"))?;
            let points = sweep_points(sweep).with_context(|| format!("{fpath}: sweep `{}`", sweep.name))?;
            for seed in &seeds {
                runs.extend(context.runs(&with_method, &method, Some(sweep), &points, *seed)?);
            }
        }
    }
    runs.sort_by(|a, b| a.key.id.cmp(&b.key.id));
    for w in runs.windows(2) {
        if w[0].key.id == w[1].key.id {
            bail!("{fpath}: two runs would share the id `{}` (two sweep points with one label?)", w[0].key.id);
        }
    }
    link_stage1_sources(file, &mut runs)?;
    Ok(Matrix { profile: profile_name.unwrap_or_else(|| "all".into()), curve_points, runs })
}

/// Ties each run of a method with `stage1_of` to the run whose stage-1 checkpoint it starts
/// from (same scene and seed): its hash covers that run's (a changed stage 1 reruns it), it
/// lands in that run's shard, and it is moved after every other run, so the source is done
/// first.
fn link_stage1_sources(file: &BenchFile, runs: &mut Vec<PlannedRun>) -> anyhow::Result<()> {
    let fpath = file.path.display();
    for i in 0..runs.len() {
        let key = &runs[i].key;
        let Some(method) = &file.methods[&key.method].stage1_of else { continue };
        let source = runs
            .iter()
            .find(|r| {
                r.key.scene == key.scene && r.key.seed == key.seed && &r.key.method == method && r.key.sweep.is_none()
            })
            .ok_or_else(|| {
                anyhow!(
                    "{fpath}: method `{}` starts from the stage 1 of method `{method}` on scene `{}`, which this \
                     profile does not run: add `{method}` to the profile's methods",
                    key.method,
                    key.scene
                )
            })?;
        let (id, hash, shard_key, skip) =
            (source.key.id.clone(), source.hash.clone(), source.shard_key.clone(), source.skip.clone());
        let run = &mut runs[i];
        run.hash = hash_text(&format!("{}\nstage 1 of {id}: {hash}", run.hash));
        run.stage1_hash = run.hash.clone();
        run.shard_key = shard_key;
        if run.skip.is_none() {
            run.skip = skip.map(|s| format!("the run it starts from, `{id}`, is skipped: {s}"));
        }
        run.stage1_of = Some(id);
    }
    // A stable partition: the order within each part stays the id order.
    let (mut later, mut first): (Vec<_>, Vec<_>) =
        std::mem::take(runs).into_iter().partition(|r| r.stage1_of.is_some());
    first.append(&mut later);
    *runs = first;
    Ok(())
}

/// One overlay of a method or sweep point.
struct Point {
    label: String,
    set: Table,
    x: Option<f64>,
}

struct RunContext<'a> {
    file: &'a BenchFile,
    scene: &'a str,
    config_dir: &'a Path,
    generate: Option<&'a Generate>,
    skip: Option<String>,
    curve_points: usize,
    view_size: Option<[u32; 2]>,
}

impl RunContext<'_> {
    /// The runs of `points` on top of `base` (a scene config with its method applied, for a
    /// sweep) at one seed.
    fn runs(
        &self,
        base: &Value,
        method: &str,
        sweep: Option<&SweepSpec>,
        points: &[Point],
        seed: u64,
    ) -> anyhow::Result<Vec<PlannedRun>> {
        let fpath = self.file.path.display();
        let mut out = Vec::new();
        for (index, point) in points.iter().enumerate() {
            let whose = match sweep {
                Some(s) => format!("sweep `{}`, point `{}`", s.name, point.label),
                None => format!("method `{method}`"),
            };
            let mut value = base.clone();
            let mut skip = self.skip.clone();
            match overlay::apply(&mut value, &point.set) {
                Ok(()) => {}
                Err(e @ OverlayError::Unregistered { .. }) => skip = skip.or(Some(e.to_string())),
                Err(e) => bail!("{fpath}: scene `{}`, {whose}: {e}", self.scene),
            }
            overlay::set(&mut value, "seed", Value::Integer(seed as i64)).expect("the root is a table");
            let shard_key = stage1_hash(&value, self.generate, self.curve_points);
            let config = if skip.is_none() {
                match check(&value) {
                    Ok(v) => v,
                    Err(message) => {
                        let culprit =
                            culprit(base, &point.set).map(|p| format!("key path `{p}`: ")).unwrap_or_default();
                        bail!("{fpath}: scene `{}`, {whose}: {culprit}{message}", self.scene)
                    }
                }
            } else {
                value
            };
            if skip.is_none() {
                skip = missing_files(&config, self.config_dir, self.generate.is_some());
            }
            let (variant, coord, slug) = match sweep {
                Some(s) => (
                    format!("{}: {}", s.name, point.label),
                    Some(SweepCoord { name: s.name.clone(), label: point.label.clone(), index, x: point.x }),
                    format!("{}-{index}-{}", s.name, slug(&point.label)),
                ),
                None => (method.to_string(), None, method.to_string()),
            };
            // The timed view's size changes what the run measures, not its stage 1.
            let mut hash = run_hash(&config, self.generate, self.curve_points);
            if let Some([w, h]) = self.view_size {
                hash = hash_text(&format!("{hash}\n# view_size = {w}x{h}\n"));
            }
            let stage1_hash = stage1_hash(&config, self.generate, self.curve_points);
            out.push(PlannedRun {
                key: RunKey {
                    id: format!("{}__{slug}__s{seed}", self.scene),
                    scene: self.scene.to_string(),
                    method: method.to_string(),
                    variant,
                    sweep: coord,
                    seed,
                },
                config_dir: self.config_dir.to_path_buf(),
                generate: self.generate.cloned(),
                config,
                hash,
                stage1_hash,
                shard_key,
                skip,
                program: None,
                stage1_of: None,
                view_size: self.view_size,
            });
        }
        Ok(out)
    }

    /// The run of a method that another build runs (`program` and `config`): its config is
    /// that build's, read as TOML with the seed and the method's `scene_keys` (taken from
    /// `scene`, this scene's resolved config) set; its hash covers the binary's bytes, so a
    /// rebuilt program runs again.
    fn program_run(&self, method: &str, scene: &Value, seed: u64) -> anyhow::Result<PlannedRun> {
        let fpath = self.file.path.display();
        let spec = &self.file.methods[method];
        let dir = self.file.dir();
        let (program, config_path) = match (&spec.program, &spec.config) {
            // Absolute, so that a bare file name is not looked up on `PATH`.
            (Some(p), Some(c)) => (std::path::absolute(dir.join(p))?, dir.join(c)),
            _ => unreachable!("checked on load: a program method has both"),
        };
        let missing = |key: &str, p: &Path| {
            (!p.is_file()).then(|| format!("path missing: {} (`{key}` of method `{method}`)", p.display()))
        };
        // Nothing of the scene applies (its config, overrides, generated layout) unless the
        // method takes some of its keys; only then do its skips.
        let takes_scene = !spec.scene_keys.is_empty();
        let skip = missing("program", &program).or_else(|| missing("config", &config_path)).or_else(|| {
            takes_scene
                .then(|| self.skip.clone().or_else(|| missing_files(scene, self.config_dir, self.generate.is_some())))?
        });
        let mut config = Value::Table(Table::new());
        if skip.is_none() {
            let text = std::fs::read_to_string(&config_path)
                .with_context(|| format!("{fpath}: method `{method}`: reading {}", config_path.display()))?;
            config = text
                .parse::<Table>()
                .map(Value::Table)
                .with_context(|| format!("{fpath}: method `{method}`: {} is not TOML", config_path.display()))?;
            overlay::set(&mut config, "seed", Value::Integer(seed as i64)).expect("the root is a table");
            for key in &spec.scene_keys {
                let value = taken_key(scene, key, self.config_dir).with_context(|| {
                    format!("{fpath}: method `{method}`, `scene_keys`: scene `{}` has no key `{key}`", self.scene)
                })?;
                overlay::set(&mut config, key, value).with_context(|| format!("{fpath}: method `{method}`"))?;
            }
        }
        // The shard key must be the same on every machine, whatever it has built.
        let mut shard_key = format!("program {}\n{method}\n{seed}", spec.program.as_ref().expect("set").display());
        if takes_scene {
            shard_key.push_str(&format!("\nscene {}", self.scene));
        }
        let shard_key = hash_text(&shard_key);
        let generate = self.generate.filter(|_| takes_scene);
        let hash = match skip {
            Some(_) => shard_key.clone(),
            None => {
                let bytes = std::fs::read(&program)
                    .with_context(|| format!("{fpath}: method `{method}`: reading {}", program.display()))?;
                let binary = hash_bytes(&bytes);
                hash_text(&format!("# program sha256 = {binary}\n{}", config_text(&config, generate)))
            }
        };
        Ok(PlannedRun {
            key: RunKey {
                id: format!("{}__{method}__s{seed}", self.scene),
                scene: self.scene.to_string(),
                method: method.to_string(),
                variant: method.to_string(),
                sweep: None,
                seed,
            },
            config_dir: config_path.parent().map(Path::to_path_buf).unwrap_or_default(),
            generate: generate.cloned(),
            config,
            stage1_hash: hash.clone(),
            hash,
            shard_key,
            skip,
            program: Some(program),
            stage1_of: None,
            view_size: None,
        })
    }
}

/// The value at dotted `key` of a scene's resolved config, for another build's config: a
/// relative `scene.path` made absolute against the scene's config folder, since the other
/// build reads it from beside its own config (`scene.masks` is relative to the path).
fn taken_key(scene: &Value, key: &str, config_dir: &Path) -> Option<Value> {
    let value = key.split('.').try_fold(scene, |node, segment| node.get(segment))?.clone();
    match value {
        Value::String(p) if key == "scene.path" && Path::new(&p).is_relative() => {
            let absolute = std::path::absolute(config_dir.join(&p)).ok()?;
            Some(Value::String(absolute.display().to_string()))
        }
        v => Some(v),
    }
}

/// Parses a config value as a run config (every section rejects unknown keys, every range is
/// checked) and returns it in canonical form.
fn check(value: &Value) -> Result<Value, String> {
    let text = toml::to_string(value).map_err(|e| e.to_string())?;
    let cfg = RunConfig::parse(&text, Path::new("<resolved>")).map_err(|e| format!("{e:#}"))?;
    Value::try_from(&cfg).map_err(|e| e.to_string())
}

/// The first path of `overlay` that alone makes `base` fail to parse.
fn culprit(base: &Value, overlay: &Table) -> Option<String> {
    overlay::flatten(overlay).into_iter().find_map(|(path, v)| {
        let mut value = base.clone();
        let bad = overlay::set(&mut value, &path, v).is_err() || check(&value).is_err();
        bad.then_some(path)
    })
}

/// Why a run cannot happen here: a data or weights file named by the config is missing.
fn missing_files(config: &Value, config_dir: &Path, generated: bool) -> Option<String> {
    let mut keys = vec!["extractor.weights", "extractor.model"];
    if !generated {
        keys.push("scene.path");
    }
    let text = |section: &str, name: &str| config.get(section)?.get(name)?.as_str().filter(|p| !p.is_empty());
    let missing =
        |key: &str, path: PathBuf| (!path.exists()).then(|| format!("path missing: {} (`{key}`)", path.display()));
    keys.into_iter()
        .find_map(|key| {
            let (section, name) = key.split_once('.').expect("dotted");
            missing(key, config_dir.join(text(section, name)?))
        })
        // A mask folder named beside the capture (LLFF's `masks`) is relative to its `path`.
        .or_else(|| missing("scene.masks", config_dir.join(text("scene", "path")?).join(text("scene", "masks")?)))
}

/// The most points one sweep may have: far more runs than any machine could train, and a
/// bound that stops a product of long lists before it fills the memory.
const MAX_SWEEP_POINTS: usize = 100_000;

/// The points of a sweep: its explicit points, or the product or zip of its `vary` lists.
fn sweep_points(sweep: &SweepSpec) -> anyhow::Result<Vec<Point>> {
    if !sweep.points.is_empty() {
        return Ok(sweep
            .points
            .iter()
            .map(|p| Point { label: p.label.clone(), set: p.set.clone(), x: None })
            .collect());
    }
    let lists: Vec<(String, Vec<Value>)> = sweep
        .vary
        .iter()
        .map(|(path, v)| match v {
            Value::Array(items) if !items.is_empty() => Ok((path.clone(), items.clone())),
            _ => Err(anyhow!("`vary.\"{path}\"` must be a non-empty list of values")),
        })
        .collect::<anyhow::Result<_>>()?;
    let combos: Vec<Vec<usize>> = match sweep.mode {
        SweepMode::Zip => {
            let n = lists[0].1.len();
            if let Some((p, l)) = lists.iter().find(|(_, l)| l.len() != n) {
                bail!("zipped lists must have one length: `{}` has {n} values, `{p}` {}", lists[0].0, l.len());
            }
            (0..n).map(|i| vec![i; lists.len()]).collect()
        }
        SweepMode::Product => {
            let points = lists.iter().try_fold(1usize, |n, (_, l)| n.checked_mul(l.len()));
            if points.is_none_or(|n| n > MAX_SWEEP_POINTS) {
                bail!(
                    "the product of its lists has more than {MAX_SWEEP_POINTS} points; vary fewer keys at once, or zip them (`mode = \"zip\"`)"
                );
            }
            lists.iter().fold(vec![Vec::new()], |acc, (_, l)| {
                acc.into_iter().flat_map(|c| (0..l.len()).map(move |i| [c.clone(), vec![i]].concat())).collect()
            })
        }
    };
    if let Some(labels) = &sweep.labels {
        if labels.len() != combos.len() {
            bail!("`labels` has {} names for {} points", labels.len(), combos.len());
        }
    }
    Ok(combos
        .iter()
        .enumerate()
        .map(|(n, combo)| {
            let mut set = Table::new();
            let mut parts = Vec::new();
            for ((path, list), &i) in lists.iter().zip(combo) {
                set.insert(path.clone(), list[i].clone());
                parts.push(if lists.len() == 1 {
                    short(&list[i])
                } else {
                    format!("{}={}", leaf(path), short(&list[i]))
                });
            }
            let x = (lists.len() == 1).then(|| number(&lists[0].1[combo[0]])).flatten();
            let label = sweep.labels.as_ref().map_or_else(|| parts.join(", "), |l| l[n].clone());
            Point { label, set, x }
        })
        .collect())
}

fn leaf(path: &str) -> &str {
    path.rsplit('.').next().unwrap_or(path)
}

/// Most items of a list written out in a label (a grid's three axes, a few steps).
const LISTED_ITEMS: usize = 4;

/// A short label for a value: scalars as written, a short list of scalars item by item
/// (`[96,96,96]`), anything else by its size.
fn short(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        Value::Integer(_) | Value::Float(_) | Value::Boolean(_) => v.to_string(),
        Value::Array(a)
            if a.len() <= LISTED_ITEMS && a.iter().all(|x| !matches!(x, Value::Array(_) | Value::Table(_))) =>
        {
            format!("[{}]", a.iter().map(short).collect::<Vec<_>>().join(","))
        }
        Value::Array(a) => format!("[{} item{}]", a.len(), if a.len() == 1 { "" } else { "s" }),
        _ => "{table}".into(),
    }
}

fn number(v: &Value) -> Option<f64> {
    match v {
        Value::Integer(i) => Some(*i as f64),
        Value::Float(f) => Some(*f),
        _ => None,
    }
}

/// A label as a file-name part.
fn slug(label: &str) -> String {
    let s: String =
        label.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '.' { c } else { '_' }).collect();
    s.chars().take(48).collect()
}

/// Hash of what decides a run's result: the config (without its generated scene's machine
/// path), the generated scene's spec, the curve sampling and the version of the rules that
/// derive settings from the scene.
fn run_hash(config: &Value, generate: Option<&Generate>, curve_points: usize) -> String {
    let mut text = config_text(config, generate);
    text.push_str(&format!("\n# curve_points = {curve_points}\n"));
    // Settings derived from the scene are not in the config: their rules' version is.
    text.push_str(&format!("# derivation = {}\n", sos_core::derived::DERIVATION_VERSION));
    hash_text(&text)
}

/// A config as hashed: a generated scene named by its spec, not by the machine's path to it.
fn config_text(config: &Value, generate: Option<&Generate>) -> String {
    let mut c = config.clone();
    if generate.is_some() {
        if let Some(scene) = c.get_mut("scene").and_then(Value::as_table_mut) {
            scene.insert("path".into(), Value::String("<generated>".into()));
        }
    }
    let mut text = toml::to_string(&c).unwrap_or_default();
    if let Some(g) = generate {
        text.push_str("\n# generate\n");
        text.push_str(&toml::to_string(&g.spec).unwrap_or_default());
    }
    text
}

/// Sections of a run config that stage 1 never reads: the head, its teacher, miner and
/// losses, stage 2's own settings and the mask rules.
const STAGE2_SECTIONS: [&str; 6] = ["segment", "head", "masks", "loss", "extractor", "miner"];

/// [`run_hash`] of the config without its [`STAGE2_SECTIONS`]: what decides stage 1.
fn stage1_hash(config: &Value, generate: Option<&Generate>, curve_points: usize) -> String {
    let mut c = config.clone();
    if let Some(t) = c.as_table_mut() {
        for section in STAGE2_SECTIONS {
            t.remove(section);
        }
    }
    run_hash(&c, generate, curve_points)
}

/// Hex SHA-256 of a text.
pub fn hash_text(text: &str) -> String {
    hash_bytes(text.as_bytes())
}

/// Hex SHA-256 of bytes.
pub(crate) fn hash_bytes(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

fn parse_generate(spec: &Table) -> anyhow::Result<Generate> {
    let mut rest = spec.clone();
    let layout = match rest.remove("layout") {
        Some(Value::String(s)) => s,
        _ => bail!("needs `layout` = one of {}", Format::ALL.map(Format::name).join(", ")),
    };
    let Some(format) = Format::ALL.into_iter().find(|f| f.name() == layout) else {
        bail!("unknown layout `{layout}`; layouts: {}", Format::ALL.map(Format::name).join(", "));
    };
    let synthetic: SyntheticConfig = Value::Table(rest).try_into().context("synthetic scene keys")?;
    synthetic.check().map_err(|e| anyhow!(e))?;
    Ok(Generate { layout: format, synthetic, spec: spec.clone() })
}

/// Work of a run that shares another's stage 1, against 1 for a run that trains its own
/// (stage 2, masks and curves are about half of a run).
const SHARED_RUN_WORK: f64 = 0.5;

/// The deterministic slice `index` of `count`. Runs with one stage 1 as the file writes it
/// (equal [`PlannedRun::shard_key`]) stay in one slice, so that they can share that stage; the
/// groups go, in the order of their first run, each to the slice with the least work so far
/// (the lowest index on a tie), a group's first run counting 1 and each further run one half.
/// Nothing machine-specific (skips, resolved settings) enters, so every machine computes the
/// same slices.
pub fn shard(runs: Vec<PlannedRun>, index: usize, count: usize) -> Vec<PlannedRun> {
    let mut groups: Vec<&str> = Vec::new();
    let mut work: Vec<f64> = Vec::new();
    let group_of: Vec<usize> = runs
        .iter()
        .map(|r| {
            let g = groups.iter().position(|&h| h == r.shard_key).unwrap_or_else(|| {
                groups.push(&r.shard_key);
                work.push(0.0);
                groups.len() - 1
            });
            work[g] += if work[g] == 0.0 { 1.0 } else { SHARED_RUN_WORK };
            g
        })
        .collect();
    // Slices past the number of stage-1 groups stay empty: no need to hold a load for each
    // (`--shard 0/1000000000000` is a valid, if pointless, request).
    let mut load = vec![0.0f64; count.min(work.len()).max(1)];
    let slice_of: Vec<usize> = work
        .iter()
        .map(|&w| {
            let least = (0..load.len()).fold(0, |best, s| if load[s] < load[best] { s } else { best });
            load[least] += w;
            least
        })
        .collect();
    runs.into_iter().zip(group_of).filter(|&(_, g)| slice_of[g] == index).map(|(r, _)| r).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use sos_plugins as _;

    /// A benchmark file and a base config in a fresh folder.
    fn bench(body: &str) -> (PathBuf, anyhow::Result<BenchFile>) {
        let dir = std::env::temp_dir().join(format!(
            "sos-matrix-{}-{}",
            std::process::id(),
            hash_text(body).get(..8).unwrap()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("base.toml"), "[scene]\nkind = \"synthetic\"\n[field]\nkind = \"voxel-grid\"\n")
            .unwrap();
        let path = dir.join("bench.toml");
        std::fs::write(&path, body).unwrap();
        (dir, BenchFile::load(&path))
    }

    const HEAD: &str = "[scenes.a]\nconfig = \"base.toml\"\n[scenes.b]\nconfig = \"base.toml\"\n[methods.default]\n[methods.short]\nset = { \"train.steps\" = 10 }\n";

    #[test]
    fn scenes_methods_seeds_and_sweeps_multiply() {
        let body = format!(
            "{HEAD}[bench]\nseeds = [0, 1]\n[[sweep]]\nname = \"s\"\nscenes = [\"a\"]\nvary = {{ \"segment.steps\" = [5, 6], \"segment.lr\" = [0.1, 0.2] }}\n"
        );
        let (dir, file) = bench(&body);
        let m = plan(&file.unwrap(), None, &dir).unwrap();
        // 2 scenes x 2 methods x 2 seeds + 4 product points x 2 seeds on one scene.
        assert_eq!(m.runs.len(), 8 + 8);
        let swept: Vec<_> = m.runs.iter().filter(|r| r.key.sweep.is_some()).collect();
        assert!(swept.iter().all(|r| r.key.scene == "a" && r.key.method == "default"));
        let steps = |r: &PlannedRun| r.config.get("segment").unwrap().get("steps").unwrap().as_integer().unwrap();
        assert!(swept.iter().any(|r| steps(r) == 6));
        // Runs with one config share a hash; different configs do not.
        let a0 = m.runs.iter().find(|r| r.key.id == "a__default__s0").unwrap();
        let b0 = m.runs.iter().find(|r| r.key.id == "b__default__s0").unwrap();
        let a1 = m.runs.iter().find(|r| r.key.id == "a__default__s1").unwrap();
        assert_eq!(a0.hash, b0.hash);
        assert_ne!(a0.hash, a1.hash);
        // Sweep points that change only stage-2 settings share the default's stage 1; another
        // stage-1 setting (the `short` method's steps) or seed does not.
        let short0 = m.runs.iter().find(|r| r.key.id == "a__short__s0").unwrap();
        assert!(swept.iter().filter(|r| r.key.seed == 0).all(|r| r.stage1_hash == a0.stage1_hash && r.hash != a0.hash));
        assert_ne!(short0.stage1_hash, a0.stage1_hash);
        assert_ne!(a1.stage1_hash, a0.stage1_hash);
    }

    #[test]
    fn a_product_too_large_to_plan_is_refused_before_it_is_built() {
        // Seven keys of 40 values: 1.6e11 points, which would fill the memory while planning.
        let values = format!("[{}]", (1..=40).map(|v| v.to_string()).collect::<Vec<_>>().join(", "));
        let keys = [
            "segment.steps",
            "segment.patches",
            "segment.stride",
            "segment.offset_grid",
            "train.steps",
            "train.rays_per_step",
            "train.samples_per_ray",
        ]
        .iter()
        .map(|k| format!("\"{k}\" = {values}"))
        .collect::<Vec<_>>()
        .join(", ");
        let body = format!("{HEAD}[[sweep]]\nname = \"huge\"\nvary = {{ {keys} }}\n");
        let (dir, file) = bench(&body);
        let err = format!("{:#}", plan(&file.unwrap(), None, &dir).err().expect("the sweep planned"));
        assert!(err.contains("sweep `huge`") && err.contains("more than 100000 points"), "{err}");
    }

    #[test]
    fn zipped_sweeps_pair_values_and_label_them() {
        let body = format!(
            "{HEAD}[[sweep]]\nname = \"z\"\nmode = \"zip\"\nscenes = [\"a\"]\nvary = {{ \"segment.steps\" = [5, 6], \"segment.lr\" = [0.1, 0.2] }}\n"
        );
        let (dir, file) = bench(&body);
        let m = plan(&file.unwrap(), None, &dir).unwrap();
        let labels: Vec<_> = m.runs.iter().filter_map(|r| r.key.sweep.as_ref().map(|s| s.label.clone())).collect();
        assert_eq!(labels.len(), 2);
        assert!(labels.contains(&"lr=0.1, steps=5".to_string()), "{labels:?}");
    }

    #[test]
    fn short_lists_are_labelled_item_by_item() {
        let grid = Value::Array(vec![Value::Integer(96); 3]);
        assert_eq!(short(&grid), "[96,96,96]");
        assert_eq!(slug(&short(&grid)), "_96_96_96_");
        assert_eq!(short(&Value::Array(vec![Value::Float(0.5); 9])), "[9 items]");
        assert_eq!(short(&Value::Array(vec![grid.clone()])), "[1 item]");
    }

    #[test]
    fn an_unknown_key_path_names_file_sweep_and_path_before_any_run() {
        let body = format!("{HEAD}[[sweep]]\nname = \"typo\"\nvary = {{ \"train.ocupancy\" = [true, false] }}\n");
        let (dir, file) = bench(&body);
        let e = format!("{:#}", plan(&file.unwrap(), None, &dir).err().unwrap());
        assert!(e.contains("bench.toml") && e.contains("sweep `typo`") && e.contains("train.ocupancy"), "{e}");
        let body = format!("{HEAD}[[sweep]]\nname = \"t2\"\nvary = {{ \"trian.steps\" = [1] }}\n");
        let (dir, file) = bench(&body);
        let e = format!("{:#}", plan(&file.unwrap(), None, &dir).err().unwrap());
        assert!(e.contains("sweep `t2`") && e.contains("trian.steps"), "{e}");
    }

    #[test]
    fn missing_data_and_unbuilt_kinds_are_skips_with_a_reason() {
        let body = format!(
            "{HEAD}[methods.vit]\nset = {{ \"extractor.kind\" = \"dino-vit\", \"extractor.weights\" = \"nope.pth\" }}\n[methods.alien]\nset = {{ \"extractor.kind\" = \"alien\" }}\n"
        );
        let (dir, file) = bench(&body);
        let m = plan(&file.unwrap(), None, &dir).unwrap();
        let vit = m.runs.iter().find(|r| r.key.method == "vit").unwrap();
        assert!(vit.skip.as_deref().unwrap().contains("path missing"), "{:?}", vit.skip);
        let alien = m.runs.iter().find(|r| r.key.method == "alien").unwrap();
        assert!(alien.skip.as_deref().unwrap().contains("not registered"), "{:?}", alien.skip);
        assert!(m.runs.iter().filter(|r| r.key.method == "default").all(|r| r.skip.is_none()));
    }

    #[test]
    fn a_mask_folder_missing_beside_its_capture_is_a_skip() {
        let dir = std::env::temp_dir().join(format!("sos-matrix-masks-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("capture").join("segments")).unwrap();
        let config = |masks: &str| -> Value {
            toml::from_str(&format!("[scene]\nkind = \"llff\"\npath = \"capture\"\nmasks = \"{masks}\"\n")).unwrap()
        };
        let why = missing_files(&config("../sam"), &dir, false).unwrap();
        assert!(why.contains("sam") && why.contains("`scene.masks`"), "{why}");
        assert_eq!(missing_files(&config("segments"), &dir, false), None);
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn another_build_takes_the_scene_keys_it_names_and_its_generated_layout() {
        let body = "[scenes.g]\nconfig = \"base.toml\"\nset = { scene = { kind = \"colmap\" }, \"train.steps\" = 7 }\n\
             generate = { layout = \"colmap\", width = 40, height = 30, views = 8 }\n\
             [scenes.h]\nconfig = \"base.toml\"\nset = { scene = { kind = \"colmap\" }, \"train.steps\" = 7 }\n\
             generate = { layout = \"colmap\", width = 40, height = 30, views = 9 }\n\
             [methods.default]\n[methods.old]\nprogram = \"old-sos\"\nconfig = \"old.toml\"\n\
             scene_keys = [\"scene.path\", \"train.steps\"]\n[profiles.p]\nmethods = [\"default\", \"old\"]\n";
        let (dir, file) = bench(body);
        let file = file.unwrap();
        std::fs::write(dir.join("old-sos"), "binary").unwrap();
        std::fs::write(dir.join("old.toml"), "[scene]\nkind = \"colmap\"\n[train]\nsteps = 1000\n[legacy]\nkey = 1\n")
            .unwrap();
        let plan_in = |out: &str| plan(&file, Some("p"), &dir.join(out)).unwrap();
        let m = plan_in("out-1");
        let old =
            |m: &Matrix, scene: &str| m.runs.iter().find(|r| r.key.id == format!("{scene}__old__s0")).cloned().unwrap();
        let default = m.runs.iter().find(|r| r.key.id == "g__default__s0").unwrap();
        let (g, h) = (old(&m, "g"), old(&m, "h"));
        assert_eq!(g.skip, None);
        // The scene's generated path and steps, the build's own other keys.
        let scene_path = default.config.get("scene").unwrap().get("path").unwrap();
        assert_eq!(g.config.get("scene").unwrap().get("path"), Some(scene_path));
        assert_eq!(g.config.get("train").unwrap().get("steps").and_then(Value::as_integer), Some(7));
        assert!(g.config.get("legacy").is_some());
        assert_eq!(g.generate.as_ref().map(|x| &x.spec), default.generate.as_ref().map(|x| &x.spec));
        // Each scene its own run and slice key; the hash does not depend on the output folder.
        assert_ne!(g.hash, h.hash);
        assert_ne!(g.shard_key, h.shard_key);
        assert_eq!(old(&plan_in("out-2"), "g").hash, g.hash);
        // A key the scene does not set is an error naming it.
        std::fs::write(dir.join("bench.toml"), body.replace("\"train.steps\"]", "\"train.nonexistent\"]")).unwrap();
        let file = BenchFile::load(&dir.join("bench.toml")).unwrap();
        let e = plan(&file, Some("p"), &dir).map(|_| ()).unwrap_err();
        assert!(format!("{e:#}").contains("train.nonexistent"), "{e:#}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn another_builds_method_runs_its_own_config_on_its_scenes_and_reruns_when_rebuilt() {
        let body = format!(
            "{HEAD}[methods.old]\nprogram = \"old-sos\"\nconfig = \"old.toml\"\nscenes = [\"a\"]\n[profiles.p]\nmethods = [\"default\", \"old\"]\n"
        );
        let (dir, file) = bench(&body);
        let file = file.unwrap();
        // Not built yet: a skip naming the key.
        let m = plan(&file, Some("p"), &dir).unwrap();
        let old: Vec<_> = m.runs.iter().filter(|r| r.key.method == "old").collect();
        assert_eq!(old.len(), 1, "only on scene `a`");
        assert!(old[0].skip.as_deref().unwrap().contains("`program` of method `old`"), "{:?}", old[0].skip);
        // Built: its config is that build's own keys (this build would refuse `legacy`), seeded.
        std::fs::write(dir.join("old-sos"), "binary one").unwrap();
        std::fs::write(dir.join("old.toml"), "name = \"x\"\n[legacy]\nkey = 1\n").unwrap();
        let m = plan(&file, Some("p"), &dir).unwrap();
        let run = m.runs.iter().find(|r| r.key.method == "old").unwrap();
        assert_eq!(run.skip, None);
        assert!(run.program.as_ref().is_some_and(|p| p.is_absolute() && p.ends_with("old-sos")));
        assert_eq!(run.config.get("seed").and_then(Value::as_integer), Some(0));
        assert!(run.config.get("legacy").is_some());
        let default = m.runs.iter().find(|r| r.key.id == "a__default__s0").unwrap();
        assert_ne!(run.stage1_hash, default.stage1_hash, "no stage 1 is shared across builds");
        // Rebuilt: the same config runs again; the shard key stays.
        std::fs::write(dir.join("old-sos"), "binary two").unwrap();
        let again = plan(&file, Some("p"), &dir).unwrap();
        let rerun = again.runs.iter().find(|r| r.key.method == "old").unwrap();
        assert_ne!(rerun.hash, run.hash);
        assert_eq!(rerun.shard_key, run.shard_key);
    }

    #[test]
    fn another_builds_stage2_follows_the_run_whose_stage1_it_starts_from() {
        let body = format!(
            "{HEAD}[bench]\nseeds = [0, 1]\n[methods.aa-old]\nprogram = \"old-sos\"\nconfig = \"old.toml\"\nstage1_of = \"short\"\n\
             [profiles.p]\nmethods = [\"aa-old\", \"default\", \"short\"]\n[profiles.q]\nmethods = [\"aa-old\", \"default\"]\n"
        );
        let (dir, file) = bench(&body);
        let file = file.unwrap();
        std::fs::write(dir.join("old-sos"), "binary").unwrap();
        std::fs::write(dir.join("old.toml"), "[legacy]\nkey = 1\n").unwrap();
        let m = plan(&file, Some("p"), &dir).unwrap();
        // Each one after its source, though its id sorts first; the rest in id order.
        let ids: Vec<&str> = m.runs.iter().map(|r| r.key.id.as_str()).collect();
        assert_eq!(&ids[8..], ["a__aa-old__s0", "a__aa-old__s1", "b__aa-old__s0", "b__aa-old__s1"]);
        assert!(ids[..8].windows(2).all(|w| w[0] < w[1]), "{ids:?}");
        for run in &m.runs[8..] {
            let source = m.runs.iter().find(|r| Some(&r.key.id) == run.stage1_of.as_ref()).unwrap();
            assert_eq!(
                (source.key.method.as_str(), &source.key.scene, source.key.seed),
                ("short", &run.key.scene, run.key.seed)
            );
            assert_eq!(run.shard_key, source.shard_key, "one shard holds both");
            assert_eq!(run.skip, None);
        }
        // A changed stage 1 of the source reruns it.
        let before = m.runs[8].hash.clone();
        std::fs::write(dir.join("bench.toml"), body.replace("\"train.steps\" = 10", "\"train.steps\" = 11")).unwrap();
        let changed = plan(&BenchFile::load(&dir.join("bench.toml")).unwrap(), Some("p"), &dir).unwrap();
        assert_ne!(changed.runs[8].hash, before);
        // A profile without the source method is an error that says what to add.
        let e = plan(&file, Some("q"), &dir).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("`aa-old`") && e.contains("add `short`"), "{e}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn shards_partition_the_matrix() {
        let (dir, file) = bench(&format!("{HEAD}[bench]\nseeds = [0, 1, 2]\n"));
        let m = plan(&file.unwrap(), None, &dir).unwrap();
        let ids: Vec<String> = m.runs.iter().map(|r| r.key.id.clone()).collect();
        let mut joined: Vec<String> = (0..3).flat_map(|i| shard(m.runs.clone(), i, 3)).map(|r| r.key.id).collect();
        joined.sort();
        assert_eq!(joined, ids);
        // Runs with one stage 1 (scenes `a` and `b` have one config) stay in one shard (every
        // 4th run of the list would split them), and the six such pairs spread evenly.
        let mut sizes = Vec::new();
        for i in 0..4 {
            let slice = shard(m.runs.clone(), i, 4);
            sizes.push(slice.len());
            for r in &slice {
                let group: Vec<_> = m.runs.iter().filter(|o| o.shard_key == r.shard_key).collect();
                assert_eq!(group.len(), 2);
                assert!(group.iter().all(|o| slice.iter().any(|x| x.key.id == o.key.id)), "{}", r.key.id);
            }
        }
        assert_eq!(sizes, [4, 4, 2, 2]);
        // Far more slices than stage-1 groups: each group alone in one of the first slices,
        // the rest empty, and no memory held for the empty ones.
        let many = 1_000_000_000_000;
        let mut firsts: Vec<String> = (0..6).flat_map(|i| shard(m.runs.clone(), i, many)).map(|r| r.key.id).collect();
        firsts.sort();
        assert_eq!(firsts, ids);
        assert!(shard(m.runs.clone(), 6, many).is_empty() && shard(m.runs.clone(), many - 1, many).is_empty());
    }
}
