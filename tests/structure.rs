//! The workspace's shape, as the groundwork issue fixed it: dependencies run one way
//! (services never depend on the simulator), every external crate is pinned once, and the
//! Lie-group math exists in one crate. Read from the manifests and sources, so a change
//! that breaks a rule fails here with the file that broke it.

use std::path::{Path, PathBuf};

/// Every `Cargo.toml` of the workspace except the root's. A manifest with its own
/// `[workspace]` table (the fuzz crate, excluded from the workspace) is not a member: it
/// cannot inherit the workspace's pins.
fn member_manifests() -> Vec<PathBuf> {
    let mut out = Vec::new();
    for dir in ["services", "ipc-schema", "hil"] {
        collect(Path::new(dir), &mut out, &|p| {
            p.file_name().is_some_and(|n| n == "Cargo.toml")
                && !std::fs::read_to_string(p)
                    .is_ok_and(|t| t.lines().any(|l| l.trim() == "[workspace]"))
        });
    }
    assert!(out.len() >= 8, "found only {out:?}");
    out
}

fn collect(dir: &Path, out: &mut Vec<PathBuf>, keep: &dyn Fn(&Path) -> bool) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() && !p.ends_with("target") {
            collect(&p, out, keep);
        } else if keep(&p) {
            out.push(p);
        }
    }
}

fn dependency_lines(manifest: &str) -> Vec<String> {
    let mut in_deps = false;
    let mut lines = Vec::new();
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_deps = line.ends_with("dependencies]");
        } else if in_deps && !line.is_empty() && !line.starts_with('#') {
            lines.push(line.to_string());
        }
    }
    lines
}

/// The lines of the sections that ship in a build: [dependencies], [build-dependencies] and
/// their target-specific forms, not [dev-dependencies] (tests may render with the simulator).
fn shipped_dependency_lines(manifest: &str) -> Vec<String> {
    let mut in_deps = false;
    let mut lines = Vec::new();
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_deps = line.ends_with("dependencies]") && !line.ends_with("dev-dependencies]");
        } else if in_deps && !line.is_empty() && !line.starts_with('#') {
            lines.push(line.to_string());
        }
    }
    lines
}

#[test]
fn services_never_depend_on_the_simulator() {
    // A service's tests may use hil (rendered flights with ground truth) as a
    // dev-dependency; the service itself never links it.
    for m in member_manifests() {
        if m.starts_with("hil") {
            continue;
        }
        let text = std::fs::read_to_string(&m).unwrap();
        for line in shipped_dependency_lines(&text) {
            assert!(
                !line.starts_with("doorslam-hil"),
                "{}: {line}: services and ipc-schema must not depend on hil",
                m.display()
            );
        }
    }
    assert!(
        shipped_dependency_lines("[dev-dependencies]\ndoorslam-hil.workspace = true\n").is_empty()
    );
    assert_eq!(
        shipped_dependency_lines("[dependencies]\ndoorslam-hil.workspace = true\n"),
        ["doorslam-hil.workspace = true"]
    );
}

#[test]
fn every_external_crate_is_pinned_once_in_the_workspace() {
    for m in member_manifests() {
        let text = std::fs::read_to_string(&m).unwrap();
        for line in dependency_lines(&text) {
            assert!(
                line.contains(".workspace = true") || line.contains("workspace = true"),
                "{}: {line}: pin it in the root [workspace.dependencies] and inherit it",
                m.display()
            );
        }
    }
}

#[test]
fn lie_group_math_exists_once() {
    let mut sources = Vec::new();
    for dir in ["services", "ipc-schema", "hil", "src"] {
        collect(Path::new(dir), &mut sources, &|p| {
            p.extension().is_some_and(|e| e == "rs")
        });
    }
    for s in sources {
        if s.starts_with("services/geometry") {
            continue;
        }
        let text = std::fs::read_to_string(&s).unwrap();
        for needle in [
            "impl LieGroup for",
            "fn so3_",
            "fn right_jacobian",
            "fn hat(",
        ] {
            assert!(
                !text.contains(needle),
                "{}: `{needle}`: SO(3)/SE(3) math belongs in services/geometry",
                s.display()
            );
        }
    }
}

/// Source files (`.rs`) of a crate folder.
fn sources_of(dir: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    collect(Path::new(dir), &mut out, &|p| {
        p.extension().is_some_and(|e| e == "rs")
    });
    assert!(!out.is_empty(), "{dir}: no sources");
    out
}

#[test]
fn opencv_feature_code_is_reached_only_through_the_vision_crate() {
    // The front-end and place recognition (and the rendezvous crate, which composes them)
    // reach OpenCV's features, descriptors, stereo, tracking and PnP only through
    // services/vision: none of them lists opencv, nor names it in a source file.
    for dir in [
        "services/frontend",
        "services/place-recognition",
        "services/rendezvous",
    ] {
        let manifest = std::fs::read_to_string(Path::new(dir).join("Cargo.toml")).unwrap();
        let lines = dependency_lines(&manifest);
        assert!(
            dir.ends_with("rendezvous") || lines.iter().any(|l| l.starts_with("doorslam-vision")),
            "{dir}/Cargo.toml: the vision crate is how it reaches image code"
        );
        for line in &lines {
            assert!(
                !line.starts_with("opencv"),
                "{dir}/Cargo.toml: {line}: OpenCV belongs to services/vision"
            );
        }
        for s in sources_of(dir) {
            let text = std::fs::read_to_string(&s).unwrap();
            for needle in ["opencv::", "use opencv", "extern crate opencv"] {
                assert!(
                    !text.contains(needle),
                    "{}: `{needle}`: OpenCV is reached through doorslam_vision",
                    s.display()
                );
            }
        }
    }
    // Only the vision crate (features, stereo, KLT, PnP) and the dataset crate (EuRoC's
    // rectification maps, when a folder is read) link OpenCV.
    for m in member_manifests() {
        let text = std::fs::read_to_string(&m).unwrap();
        if dependency_lines(&text)
            .iter()
            .any(|l| l.starts_with("opencv"))
        {
            assert!(
                m.starts_with("services/vision") || m.starts_with("services/dataset"),
                "{}: depends on opencv directly",
                m.display()
            );
        }
    }
}

#[test]
fn the_front_end_and_place_recognition_do_not_depend_on_each_other() {
    for (dir, other, module) in [
        (
            "services/frontend",
            "doorslam-place-recognition",
            "doorslam_place_recognition",
        ),
        (
            "services/place-recognition",
            "doorslam-frontend",
            "doorslam_frontend",
        ),
    ] {
        let manifest = std::fs::read_to_string(Path::new(dir).join("Cargo.toml")).unwrap();
        for line in dependency_lines(&manifest) {
            assert!(
                !line.starts_with(other),
                "{dir}/Cargo.toml: {line}: the two services share code only through services/vision"
            );
        }
        for s in sources_of(dir) {
            let text = std::fs::read_to_string(&s).unwrap();
            // Doc comments may name the other crate; code may not use it.
            for (n, line) in text.lines().enumerate() {
                let code = line.trim_start();
                if code.starts_with("//") {
                    continue;
                }
                assert!(
                    !code.contains(&format!("{module}::")),
                    "{}:{}: uses {module}",
                    s.display(),
                    n + 1
                );
            }
        }
    }
}
