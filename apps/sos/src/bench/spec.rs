//! The benchmark file: scenes, methods, sweeps and profiles, read from TOML.
//!
//! ```toml
//! [bench]
//! baseline = "default"      # the method every speed-up is measured against
//! curve_points = 6          # learning-curve samples per stage
//! seeds = [0]
//! default_profile = "quick"
//! target = { miou = 0.95, nv_ari = 0.93 }   # the report's time-to-target column
//! view_size = [504, 378]    # the view each run times with its mask (default: the scene's size)
//!
//! [scenes.object-centric]
//! config = "../configs/synthetic.toml"          # base run config, relative to this file
//! set = { "train.steps" = 300 }                   # overrides by dotted path
//!
//! [scenes.llff-layout]
//! config = "bare.toml"                         # only `[scene] kind`
//! set = { scene = { kind = "llff" } }
//! generate = { layout = "llff", width = 100, height = 75, views = 24 }
//!
//! [methods.default]
//! [methods.no-geometry]
//! set = { loss = [{ kind = "appearance", weight = 1.0 }] }
//! [methods.older-build]                        # another build's `sos train` on its own config
//! program = "../target/builds/b3a6cd8/sos"
//! config = "../target/builds/b3a6cd8/src/configs/synthetic.toml"
//! scenes = ["object-centric"]
//! [methods.older-build-on-layouts]             # the same, given each scene's generated layout
//! program = "../target/builds/b3a6cd8/sos"
//! config = "older-colmap.toml"
//! scene_keys = ["scene.path", "train.steps"]
//! [methods.older-build-stage2]                 # its `sos segment` from the default run's stage 1
//! program = "../target/builds/b3a6cd8/sos"
//! config = "older-nerf.toml"
//! stage1_of = "default"
//!
//! [[sweep]]
//! name = "head-steps"
//! vary = { "segment.steps" = [50, 100, 200] }
//!
//! [profiles.quick]
//! scenes = ["object-centric", "llff-layout"]
//! methods = ["default"]
//! sweeps = ["head-steps"]
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use serde::Deserialize;

/// Largest side of the timed view: a 16k view with its mask is already minutes of work.
const MAX_VIEW_SIDE: u32 = 16384;

/// Most learning-curve points per stage: each is a held-out evaluation.
const MAX_CURVE_POINTS: usize = 1000;

/// A parsed benchmark file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BenchFile {
    /// Settings of the whole benchmark.
    #[serde(default)]
    pub bench: BenchSettings,
    /// Scenes by name.
    #[serde(default)]
    pub scenes: BTreeMap<String, SceneSpec>,
    /// Methods (named config overlays) by name.
    #[serde(default)]
    pub methods: BTreeMap<String, MethodSpec>,
    /// Sweeps over config keys.
    #[serde(default)]
    pub sweep: Vec<SweepSpec>,
    /// Named subsets of the matrix.
    #[serde(default)]
    pub profiles: BTreeMap<String, ProfileSpec>,
    /// Where the file was read from (its folder resolves relative paths).
    #[serde(skip)]
    pub path: PathBuf,
}

/// `[bench]`.
#[derive(Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BenchSettings {
    /// The method of the speed-up column.
    pub baseline: String,
    /// Learning-curve samples per stage (0 = no curves).
    pub curve_points: usize,
    /// Seeds of every run (a profile may override them).
    pub seeds: Vec<u64>,
    /// The profile `sos bench` runs without `--profile` (none: every scene, method and sweep).
    pub default_profile: Option<String>,
    /// Output folder, relative to the benchmark file (`--out` overrides it).
    pub out: PathBuf,
    /// The quality whose wall time to reach the report gives per run (none: no such column).
    pub target: Option<super::target::Target>,
    /// `[width, height]` of the view each run times with its mask (none: the scene's own size).
    pub view_size: Option<[u32; 2]>,
}

impl Default for BenchSettings {
    fn default() -> Self {
        BenchSettings {
            baseline: "default".into(),
            curve_points: 6,
            seeds: vec![0],
            default_profile: None,
            out: PathBuf::from("../runs/bench"),
            target: None,
            view_size: None,
        }
    }
}

/// `[scenes.<name>]`: a base run config and overrides.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// Base run config, relative to the benchmark file.
    pub config: PathBuf,
    /// Overrides by dotted key path.
    #[serde(default)]
    pub set: toml::Table,
    /// Write the built-in synthetic scene in a dataset layout first and read it from there:
    /// `layout` (`llff`, `blender`, `colmap`, `colmap_txt`, `blendedmvs`, `blendedmvs_nsvf`,
    /// `co3d`, `tanks_temples`) plus any key of the `synthetic` dataset (`rig`, `width`, ...).
    pub generate: Option<toml::Table>,
    /// One line for the report.
    #[serde(default)]
    pub about: String,
}

/// `[methods.<name>]`: a named overlay on every scene's config, or another build's run.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MethodSpec {
    /// Overrides by dotted key path.
    #[serde(default)]
    pub set: toml::Table,
    /// One line for the report.
    #[serde(default)]
    pub about: String,
    /// Scenes the method runs on (default: every scene of the profile).
    pub scenes: Option<Vec<String>>,
    /// Another `sos` build (its binary, relative to this file) that runs the method with its own
    /// `sos train`, so that one report compares builds; needs `config`.
    pub program: Option<PathBuf>,
    /// With `program`: the whole run config in that build's own keys (relative to this file).
    /// The scene's config and overrides do not apply: the row is that build's run, set beside
    /// the scene's other rows.
    pub config: Option<PathBuf>,
    /// With `program`: dotted keys the other build's config takes from each scene's config as
    /// this file resolves it (e.g. `scene.path` of a generated layout, `train.steps`), for keys
    /// both builds read alike. A generated scene is then written before the run.
    #[serde(default)]
    pub scene_keys: Vec<String>,
    /// With `program`: the other build starts from the stage-1 checkpoint of this method's run
    /// (same scene and seed, this build's, in the same invocation) with its own
    /// `sos segment --checkpoint`, instead of training its own stage 1: both builds' stage 2
    /// then run on one field, and an hour-long stage 1 is trained once.
    pub stage1_of: Option<String>,
}

/// How a sweep combines the lists of its `vary` keys.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SweepMode {
    /// Every combination (cartesian product).
    #[default]
    Product,
    /// The i-th value of every list together (lists of equal length).
    Zip,
}

/// `[[sweep]]`: runs that vary config keys on top of a method.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepSpec {
    /// Name (unique).
    pub name: String,
    /// The method the sweep varies (default: the baseline).
    pub method: Option<String>,
    /// Scenes the sweep runs on (default: every scene of the profile); only those the profile
    /// also runs are used.
    pub scenes: Option<Vec<String>>,
    /// Dotted key path → list of values.
    #[serde(default)]
    pub vary: toml::Table,
    /// How the `vary` lists combine.
    #[serde(default)]
    pub mode: SweepMode,
    /// Names of the points in order (default: `key=value`).
    pub labels: Option<Vec<String>>,
    /// Explicit points instead of `vary`: each a label and overrides.
    #[serde(default)]
    pub points: Vec<SweepPoint>,
    /// One line for the report.
    #[serde(default)]
    pub about: String,
}

/// One explicit point of a sweep.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepPoint {
    /// Name of the point in the report.
    pub label: String,
    /// Overrides by dotted key path.
    #[serde(default)]
    pub set: toml::Table,
}

/// `[profiles.<name>]`: which scenes, methods, sweeps and seeds run.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProfileSpec {
    /// Scene names (default: every scene).
    pub scenes: Option<Vec<String>>,
    /// Method names (default: every method).
    pub methods: Option<Vec<String>>,
    /// Sweep names (default: none).
    #[serde(default)]
    pub sweeps: Vec<String>,
    /// Seeds (default: `[bench] seeds`).
    pub seeds: Option<Vec<u64>>,
    /// Learning-curve samples per stage (default: `[bench] curve_points`).
    pub curve_points: Option<usize>,
    /// Size of the timed view (default: `[bench] view_size`).
    pub view_size: Option<[u32; 2]>,
    /// Overrides applied to every run of the profile, after the scene's and before the
    /// method's.
    #[serde(default)]
    pub set: toml::Table,
    /// One line for the report.
    #[serde(default)]
    pub about: String,
}

impl BenchFile {
    /// Reads and checks a benchmark file; errors name the file and the entry.
    pub fn load(path: &Path) -> anyhow::Result<BenchFile> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading benchmark file {}", path.display()))?;
        let mut file: BenchFile =
            toml::from_str(&text).with_context(|| format!("benchmark file {}", path.display()))?;
        file.path = path.to_path_buf();
        file.check()?;
        Ok(file)
    }

    /// The folder relative paths start from.
    pub fn dir(&self) -> PathBuf {
        self.path.parent().map(Path::to_path_buf).unwrap_or_default()
    }

    /// Cross-references: every name a profile or sweep uses exists, names are unique and
    /// file-safe.
    fn check(&self) -> anyhow::Result<()> {
        let file = self.path.display();
        if self.scenes.is_empty() {
            bail!("{file}: no `[scenes.<name>]` entry; add at least one scene");
        }
        if let Some(Err(why)) = self.bench.target.as_ref().map(super::target::Target::check) {
            bail!("{file}: `bench.target` {why}");
        }
        let sizes = std::iter::once(("`bench.view_size`".to_string(), self.bench.view_size))
            .chain(self.profiles.iter().map(|(name, p)| (format!("profile `{name}`, `view_size`"), p.view_size)));
        for (what, size) in sizes {
            if let Some([w, h]) = size {
                if !(1..=MAX_VIEW_SIDE).contains(&w) || !(1..=MAX_VIEW_SIDE).contains(&h) {
                    bail!("{file}: {what} is {w}x{h}; give a width and height from 1 to {MAX_VIEW_SIDE}");
                }
            }
        }
        let curves = std::iter::once(("`bench.curve_points`".to_string(), Some(self.bench.curve_points)))
            .chain(self.profiles.iter().map(|(name, p)| (format!("profile `{name}`, `curve_points`"), p.curve_points)));
        for (what, points) in curves {
            // Each point is a held-out evaluation: more than a stage has steps is pointless,
            // and a huge count costs a check on every step.
            if points.is_some_and(|n| n > MAX_CURVE_POINTS) {
                bail!("{file}: {what} is {}; give at most {MAX_CURVE_POINTS} (0: no curve)", points.unwrap_or(0));
            }
        }
        if !self.methods.contains_key(&self.bench.baseline) {
            bail!(
                "{file}: `bench.baseline` names method `{}`, which is not defined; methods: {}",
                self.bench.baseline,
                names(self.methods.keys())
            );
        }
        for name in self.scenes.keys().chain(self.methods.keys()).chain(self.sweep.iter().map(|s| &s.name)) {
            if !is_safe_name(name) {
                bail!("{file}: name `{name}` may only hold letters, digits, `-` and `_`");
            }
        }
        for (name, m) in &self.methods {
            for scene in m.scenes.iter().flatten() {
                if !self.scenes.contains_key(scene) {
                    bail!(
                        "{file}: method `{name}` names scene `{scene}`, which is not defined; scenes: {}",
                        names(self.scenes.keys())
                    );
                }
            }
            if m.program.is_none() && !m.scene_keys.is_empty() {
                bail!("{file}: method `{name}` sets `scene_keys`, which only a method run by another build (`program`) takes");
            }
            if let Some(source) = &m.stage1_of {
                if m.program.is_none() {
                    bail!("{file}: method `{name}` sets `stage1_of`, which only a method run by another build (`program`) takes");
                }
                match self.methods.get(source) {
                    Some(s) if s.program.is_none() => {}
                    Some(_) => bail!(
                        "{file}: method `{name}`: `stage1_of = \"{source}\"` names a method run by another build; \
                         name one of this build's, whose run writes the stage-1 checkpoint"
                    ),
                    None => bail!(
                        "{file}: method `{name}`: `stage1_of` names method `{source}`, which is not defined; methods: {}",
                        names(self.methods.keys())
                    ),
                }
            }
            match (&m.program, &m.config) {
                (None, None) => {}
                (Some(_), Some(_)) if m.set.is_empty() => {}
                (Some(_), Some(_)) => bail!(
                    "{file}: method `{name}` runs another build (`program`), whose keys this build cannot check: \
                     write its overrides into its `config` instead of `set`"
                ),
                _ => bail!("{file}: method `{name}` needs both `program` (another build's `sos`) and `config` (its run config), or neither"),
            }
        }
        if self.methods[&self.bench.baseline].program.is_some() {
            bail!(
                "{file}: the baseline method `{}` runs another build; the baseline must be this build's",
                self.bench.baseline
            );
        }
        let mut seen = std::collections::BTreeSet::new();
        for s in &self.sweep {
            if !seen.insert(&s.name) {
                bail!("{file}: two sweeps are named `{}`", s.name);
            }
            if let Some(m) = &s.method {
                match self.methods.get(m) {
                    None => bail!(
                        "{file}: sweep `{}` varies method `{m}`, which is not defined; methods: {}",
                        s.name,
                        names(self.methods.keys())
                    ),
                    Some(spec) if spec.program.is_some() => bail!(
                        "{file}: sweep `{}` varies method `{m}`, which runs another build: its keys cannot be varied here",
                        s.name
                    ),
                    Some(_) => {}
                }
            }
            for scene in s.scenes.iter().flatten() {
                if !self.scenes.contains_key(scene) {
                    bail!(
                        "{file}: sweep `{}` names scene `{scene}`, which is not defined; scenes: {}",
                        s.name,
                        names(self.scenes.keys())
                    );
                }
            }
            if s.vary.is_empty() == s.points.is_empty() {
                bail!(
                    "{file}: sweep `{}` needs either `vary` (key path = [values]) or `points`, not both or neither",
                    s.name
                );
            }
        }
        for (name, p) in &self.profiles {
            for scene in p.scenes.iter().flatten() {
                if !self.scenes.contains_key(scene) {
                    bail!(
                        "{file}: profile `{name}` names scene `{scene}`, which is not defined; scenes: {}",
                        names(self.scenes.keys())
                    );
                }
            }
            for method in p.methods.iter().flatten() {
                if !self.methods.contains_key(method) {
                    bail!(
                        "{file}: profile `{name}` names method `{method}`, which is not defined; methods: {}",
                        names(self.methods.keys())
                    );
                }
            }
            for sweep in &p.sweeps {
                if !self.sweep.iter().any(|s| &s.name == sweep) {
                    bail!(
                        "{file}: profile `{name}` names sweep `{sweep}`, which is not defined; sweeps: {}",
                        names(self.sweep.iter().map(|s| &s.name))
                    );
                }
            }
        }
        if let Some(p) = &self.bench.default_profile {
            if !self.profiles.contains_key(p) {
                bail!(
                    "{file}: `bench.default_profile` names profile `{p}`, which is not defined; profiles: {}",
                    names(self.profiles.keys())
                );
            }
        }
        Ok(())
    }
}

/// Names for run ids and folders: letters, digits, `-`, `_`.
pub fn is_safe_name(name: &str) -> bool {
    !name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// `a, b, c` (or `(none)`).
pub fn names<'a>(items: impl Iterator<Item = &'a String>) -> String {
    let all: Vec<&str> = items.map(String::as_str).collect();
    if all.is_empty() {
        "(none)".into()
    } else {
        all.join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> anyhow::Result<BenchFile> {
        let mut file: BenchFile = toml::from_str(text)?;
        file.path = PathBuf::from("bench.toml");
        file.check()?;
        Ok(file)
    }

    const MINIMAL: &str = r#"
[scenes.a]
config = "a.toml"
[methods.default]
"#;

    #[test]
    fn a_minimal_file_parses_with_defaults() {
        let file = parse(MINIMAL).unwrap();
        assert_eq!(file.bench.baseline, "default");
        assert_eq!(file.bench.seeds, vec![0]);
        assert!(file.sweep.is_empty());
    }

    #[test]
    fn names_that_do_not_exist_are_errors_naming_them() {
        let e = parse(&format!("{MINIMAL}[profiles.q]\nscenes = [\"b\"]\n")).unwrap_err().to_string();
        assert!(e.contains("profile `q`") && e.contains("scene `b`"), "{e}");
        let e = parse(&format!("{MINIMAL}[[sweep]]\nname = \"s\"\nmethod = \"m\"\nvary = {{ seed = [1] }}\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("sweep `s`") && e.contains("method `m`"), "{e}");
        let e = parse("[bench]\nbaseline = \"x\"\n[scenes.a]\nconfig = \"a.toml\"\n[methods.default]\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("bench.baseline"), "{e}");
    }

    #[test]
    fn a_sweep_needs_vary_or_points() {
        let e = parse(&format!("{MINIMAL}[[sweep]]\nname = \"s\"\n")).unwrap_err().to_string();
        assert!(e.contains("either `vary`"), "{e}");
    }

    #[test]
    fn a_method_run_by_another_build_needs_its_config_and_no_overrides() {
        let with =
            |body: &str| parse(&format!("{MINIMAL}[methods.old]\n{body}")).map(|_| ()).map_err(|e| e.to_string());
        assert!(with("program = \"old/sos\"\nconfig = \"old.toml\"\nscenes = [\"a\"]\n").is_ok());
        let e = with("program = \"old/sos\"\n").unwrap_err();
        assert!(e.contains("method `old`") && e.contains("`config`"), "{e}");
        let e = with("program = \"old/sos\"\nconfig = \"old.toml\"\nset = { seed = 1 }\n").unwrap_err();
        assert!(e.contains("`set`"), "{e}");
        let e = with("scene_keys = [\"scene.path\"]\n").unwrap_err();
        assert!(e.contains("method `old`") && e.contains("`scene_keys`"), "{e}");
        let e = with("scenes = [\"b\"]\n").unwrap_err();
        assert!(e.contains("method `old`") && e.contains("scene `b`"), "{e}");
        let e = with(
            "program = \"o\"\nconfig = \"o.toml\"\n[[sweep]]\nname = \"s\"\nmethod = \"old\"\nvary = { seed = [1] }\n",
        )
        .unwrap_err();
        assert!(e.contains("sweep `s`") && e.contains("another build"), "{e}");
        let program = "program = \"o\"\nconfig = \"o.toml\"\n";
        assert!(with(&format!("{program}stage1_of = \"default\"\n")).is_ok());
        let e = with("stage1_of = \"default\"\n").unwrap_err();
        assert!(e.contains("method `old`") && e.contains("`stage1_of`"), "{e}");
        let e = with(&format!("{program}stage1_of = \"nope\"\n")).unwrap_err();
        assert!(e.contains("`nope`") && e.contains("not defined"), "{e}");
        let e = with(&format!("{program}stage1_of = \"old\"\n")).unwrap_err();
        assert!(e.contains("another build"), "{e}");
    }

    #[test]
    fn unsafe_names_are_refused() {
        let e = parse("[scenes.\"a/b\"]\nconfig = \"a.toml\"\n[methods.default]\n").unwrap_err().to_string();
        assert!(e.contains("a/b"), "{e}");
    }
}
