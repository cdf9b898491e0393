//! The plan library: a folder of plan configurations the daemon's configuration names
//! (`plan_library`), listed and submitted by name. Only regular `.toml` files directly in
//! the folder whose resolved path (symlinks followed) stays inside it are offered: a request
//! names a plan, never a path.

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// A plan of the library.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct LibraryPlan {
    /// Its file name (`nightly.toml`): what `POST /v1/plans/{name}/submit` takes.
    pub name: String,
    /// Its `kind` key, when it has one that parses.
    pub kind: Option<String>,
    /// Its `[machine] name`, when it has one.
    pub machine: Option<String>,
    pub bytes: u64,
}

/// The library folder, resolved once at the daemon's start.
#[derive(Debug, Clone)]
pub struct PlanLibrary {
    dir: PathBuf,
}

impl PlanLibrary {
    /// The folder `plan_library` names, which must exist.
    pub fn open(dir: &Path) -> anyhow::Result<PlanLibrary> {
        let resolved = std::fs::canonicalize(dir)
            .ok()
            .filter(|d| d.is_dir())
            .with_context(|| {
                format!(
                    "plan_library = \"{}\": expected an existing folder",
                    dir.display()
                )
            })?;
        Ok(PlanLibrary { dir: resolved })
    }

    /// Every plan offered, by name.
    pub fn list(&self) -> Vec<LibraryPlan> {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return Vec::new();
        };
        let mut plans: Vec<LibraryPlan> = entries
            .filter_map(|entry| entry.ok()?.file_name().into_string().ok())
            .filter_map(|name| {
                let path = self.resolve(&name)?;
                let text = std::fs::read_to_string(&path).ok()?;
                let table = text.parse::<toml::Table>().ok();
                let field = |section: Option<&str>, key: &str| {
                    let table = table.as_ref()?;
                    let scope = match section {
                        Some(s) => table.get(s)?.as_table()?,
                        None => table,
                    };
                    scope.get(key)?.as_str().map(str::to_owned)
                };
                Some(LibraryPlan {
                    kind: field(None, "kind"),
                    machine: field(Some("machine"), "name"),
                    bytes: text.len() as u64,
                    name,
                })
            })
            .collect();
        plans.sort_by(|a, b| a.name.cmp(&b.name));
        plans
    }

    /// The text of plan `name`, or None when the library offers no such plan.
    pub fn read(&self, name: &str) -> Option<String> {
        std::fs::read_to_string(self.resolve(name)?).ok()
    }

    /// The file of plan `name` when it is offered: a plain `.toml` name (no separator, not
    /// hidden) whose resolved path is a regular file inside the folder.
    fn resolve(&self, name: &str) -> Option<PathBuf> {
        let plain = name.ends_with(".toml")
            && !name.starts_with('.')
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
        if !plain {
            return None;
        }
        let path = std::fs::canonicalize(self.dir.join(name)).ok()?;
        (path.parent() == Some(self.dir.as_path()) && path.is_file()).then_some(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_plain_toml_files_inside_the_folder_are_offered() {
        let root = tempfile::tempdir().unwrap();
        let library = root.path().join("plans");
        std::fs::create_dir(&library).unwrap();
        std::fs::write(
            library.join("demo.toml"),
            "kind = \"multilateration\"\n[machine]\nname = \"M\"\n",
        )
        .unwrap();
        std::fs::write(library.join("notes.txt"), "x").unwrap();
        std::fs::write(library.join(".hidden.toml"), "kind = \"x\"").unwrap();
        std::fs::write(root.path().join("outside.toml"), "kind = \"secret\"").unwrap();
        std::os::unix::fs::symlink(root.path().join("outside.toml"), library.join("link.toml"))
            .unwrap();
        std::fs::create_dir(library.join("dir.toml")).unwrap();
        let plans = PlanLibrary::open(&library).unwrap();
        let listed = plans.list();
        assert_eq!(listed.len(), 1, "{listed:?}");
        assert_eq!(listed[0].name, "demo.toml");
        assert_eq!(listed[0].kind.as_deref(), Some("multilateration"));
        assert_eq!(listed[0].machine.as_deref(), Some("M"));
        assert!(plans.read("demo.toml").is_some());
        for refused in [
            "link.toml",
            "../outside.toml",
            ".hidden.toml",
            "notes.txt",
            "dir.toml",
            "missing.toml",
        ] {
            assert!(plans.read(refused).is_none(), "{refused}");
        }
        assert!(PlanLibrary::open(&root.path().join("none")).is_err());
    }
}
