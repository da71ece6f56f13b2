//! Imports split across machines (`isovox import ... --part I/N`, then `--finish`) and
//! multipart uploads, against the real S3 server of [`crate::object_store`] (moto), with the
//! binary run as processes:
//!
//! - four parts run as four concurrent processes, then the finish, make the volume the
//!   single-process import of the same input makes: every level of density and of its
//!   `material` channel byte for byte (the reference is that import, an independent run of the
//!   whole pipeline in one process);
//! - a part killed with SIGKILL between two rows is run again, resumes from the rows it
//!   stored, and the finish gives the same volume; a finished part run again is skipped;
//! - the finish refuses a missing part, or parts of different volumes, naming the part;
//! - a segment above the multipart threshold goes up as a multipart upload (its ETag is S3's
//!   multipart form, `md5-N`) and reads back equal;
//! - the Kubernetes manifests in `docker/k8s/` validate against the Kubernetes schemas.

use crate::object_store::S3;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// The generated world: 96 x 64 x 128 voxels, bricks of 16: 8 brick rows, 2 per part of 4.
const DIMS: &str = "96,64,128";
const BRICK: &str = "16";

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `isovox` with the store's environment and `envs`, its output (not checked).
fn run(s3: &S3, args: &[&str], envs: &[(&str, &str)]) -> Output {
    isovox(s3, args)
        .envs(envs.iter().copied())
        .output()
        .unwrap()
}

/// `isovox args`, with the S3 server's endpoint and credentials in its environment.
fn isovox(s3: &S3, args: &[&str]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_isovox"));
    cmd.args(args);
    s3.env(&mut cmd);
    cmd
}

/// `isovox` that must succeed: its stdout and stderr.
fn ok(s3: &S3, args: &[&str], envs: &[(&str, &str)]) -> (String, String) {
    let out = run(s3, args, envs);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    );
    assert!(out.status.success(), "isovox {args:?}: {stderr}");
    (stdout, stderr)
}

/// A world with a `material` channel, written as OME-Zarr: the input of every import here
/// (a field format, so its label map comes in as a channel with `--channel`).
fn zarr_input(dir: &Path) -> (String, String) {
    let vod = dir.join("world.vod");
    let zarr = dir.join("world.zarr");
    crate::server_process::run_isovox(&[
        "generate",
        "world",
        "--materials",
        "--dims",
        DIMS,
        "--brick",
        BRICK,
        "-o",
        vod.to_str().unwrap(),
    ]);
    crate::server_process::run_isovox(&[
        "export",
        vod.to_str().unwrap(),
        "--format",
        "zarr",
        "-o",
        zarr.to_str().unwrap(),
    ]);
    let image = zarr.to_str().unwrap().to_string();
    let labels = format!("material={}", zarr.join("labels/material/0").display());
    (image, labels)
}

/// The import arguments of `input` into `volume`, then `more`.
fn import_args<'a>(input: &'a (String, String), volume: &'a str, more: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec![
        "import",
        input.0.as_str(),
        "--channel",
        input.1.as_str(),
        "--brick",
        BRICK,
        "-o",
        volume,
    ];
    args.extend_from_slice(more);
    args
}

/// Every file below `dir`, by relative path, with its bytes.
fn tree(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let rel = path.strip_prefix(dir).unwrap().display().to_string();
                out.push((rel, std::fs::read(&path).unwrap()));
            }
        }
    }
    out.sort();
    out
}

/// Every level of `volume`, density and channel, as files: its OME-Zarr export (each level of
/// the image and of `labels/material`), and density's levels as RAW (`isovox export --level`).
fn levels(s3: &S3, volume: &str, dir: &Path, tag: &str) -> Vec<(String, Vec<u8>)> {
    let zarr = dir.join(format!("{tag}.zarr"));
    ok(
        s3,
        &[
            "export",
            volume,
            "--format",
            "zarr",
            "-o",
            zarr.to_str().unwrap(),
        ],
        &[],
    );
    let mut files = tree(&zarr);
    // The export names the view after the volume in its metadata; all else must agree byte
    // for byte.
    for (name, bytes) in &mut files {
        if name.ends_with(".json") {
            *bytes = String::from_utf8_lossy(bytes)
                .replace(tag, "VOLUME")
                .into_bytes();
        }
    }
    for level in 0..4 {
        let raw = dir.join(format!("{tag}-{level}.raw"));
        ok(
            s3,
            &[
                "export",
                volume,
                "--level",
                &level.to_string(),
                "-o",
                raw.to_str().unwrap(),
            ],
            &[],
        );
        files.push((format!("raw level {level}"), std::fs::read(&raw).unwrap()));
    }
    files
}

fn assert_same_levels(a: &[(String, Vec<u8>)], b: &[(String, Vec<u8>)]) {
    let names = |v: &[(String, Vec<u8>)]| v.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
    assert_eq!(names(a), names(b), "the same files");
    for ((name, x), (_, y)) in a.iter().zip(b) {
        assert!(x == y, "{name} differs ({} and {} bytes)", x.len(), y.len());
    }
    // Not vacuous: the levels hold terrain and materials, not only air.
    let level0 = &a.iter().find(|(n, _)| n == "raw level 0").unwrap().1;
    assert_eq!(level0.len(), 96 * 64 * 128);
    assert!(level0.iter().any(|&v| v != 0) && level0.contains(&0));
    assert!(
        a.iter().any(|(n, _)| n.starts_with("labels/material/2/")),
        "the channel's level 2 is compared: {:?}",
        names(a)
    );
}

/// The objects below a volume's `parts/`.
fn part_objects(s3: &S3, name: &str) -> Vec<String> {
    volume_bucket(s3, name)
        .list("parts")
        .unwrap()
        .into_iter()
        .map(|o| o.key)
        .collect()
}

fn volume_bucket(s3: &S3, name: &str) -> isovox_server::store::remote::Bucket {
    std::env::set_var("AWS_ACCESS_KEY_ID", "isovox");
    std::env::set_var("AWS_SECRET_ACCESS_KEY", "isovox-secret");
    std::env::set_var("AWS_REGION", "us-east-1");
    isovox_server::store::remote::Bucket::from_url_at(&s3.url(), Some(&s3.endpoint))
        .unwrap()
        .child(name)
}

/// The bytes of volume `name`'s one segment before its commit record: its header, bricks and
/// index (the commit record holds the time of the commit, the one thing two builds of the same
/// input differ in).
fn before_commit(s3: &S3, name: &str) -> Vec<u8> {
    let bucket = volume_bucket(s3, name);
    let (head, _) = isovox_server::store::remote::read_head(&bucket).unwrap();
    assert_eq!(head.segments.len(), 1);
    let bytes = bucket.get(&head.segments[0].key).unwrap().unwrap();
    bytes[..head.commit as usize].to_vec()
}

/// The single-process import of `input` into `vols/single`, and its levels.
fn reference(s3: &S3, input: &(String, String), dir: &Path) -> Vec<(String, Vec<u8>)> {
    let single = format!("{}/single", s3.url());
    ok(s3, &import_args(input, &single, &[]), &[]);
    levels(s3, &single, dir, "single")
}

#[test]
fn four_concurrent_parts_and_a_finish_make_the_single_import_s_volume() {
    let s3 = S3::start("split-four");
    let dir = tempfile::tempdir().unwrap();
    let input = zarr_input(dir.path());
    let expected = reference(&s3, &input, dir.path());

    let volume = format!("{}/split", s3.url());
    let start = Instant::now();
    let children: Vec<_> = (0..4)
        .map(|i| {
            let part = format!("{i}/4");
            isovox(&s3, &import_args(&input, &volume, &["--part", &part]))
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for (i, child) in children.into_iter().enumerate() {
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "part {i}/4: {stderr}");
        let stdout = String::from_utf8_lossy(&out.stdout);
        // 8 brick rows in 4 parts: 2 each, 2 streams (density, material): 4 row objects.
        let rows = format!("brick rows {}..{}", 2 * i, 2 * i + 2);
        assert!(stdout.contains(&rows), "part {i}/4 says {stdout}");
        assert!(stdout.contains("4 row objects"), "part {i}/4 says {stdout}");
    }
    // Nothing is a volume before the finish: no head, no segment.
    assert!(isovox_server::store::remote::read_head(&volume_bucket(&s3, "split")).is_err());
    let (stdout, stderr) = ok(&s3, &["import", "--finish", "-o", &volume], &[]);
    eprintln!(
        "4 parts and the finish in {:.2} s",
        start.elapsed().as_secs_f64()
    );
    assert!(stdout.contains("from 4 parts"), "{stdout}");
    assert!(
        stderr.contains("building: 100%"),
        "progress on stderr: {stderr}"
    );
    assert_eq!(
        part_objects(&s3, "split"),
        Vec::<String>::new(),
        "the parts are deleted once the volume is committed"
    );
    assert_same_levels(&levels(&s3, &volume, dir.path(), "split"), &expected);
    // More than the voxels: the same file, bricks and index alike.
    assert!(before_commit(&s3, "split") == before_commit(&s3, "single"));

    // A second finish changes nothing and says why.
    let again = run(&s3, &["import", "--finish", "-o", &volume], &[]);
    assert!(!again.status.success());
    let e = String::from_utf8_lossy(&again.stderr);
    assert!(e.contains("exists already"), "{e}");
}

#[test]
fn a_part_killed_mid_way_resumes_and_a_finished_part_is_skipped() {
    let s3 = S3::start("split-kill");
    let dir = tempfile::tempdir().unwrap();
    let input = zarr_input(dir.path());
    let expected = reference(&s3, &input, dir.path());
    let volume = format!("{}/killed", s3.url());
    for i in [0, 1, 3] {
        ok(
            &s3,
            &import_args(&input, &volume, &["--part", &format!("{i}/4")]),
            &[],
        );
    }

    // Part 2 waits after each row it stores; it is killed after its first.
    let mut child = isovox(&s3, &import_args(&input, &volume, &["--part", "2/4"]))
        .env("ISOVOX_PART_PAUSE_AFTER_ROW_MS", "60000")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let line = lines
            .next()
            .expect("part 2/4 says it stored a row")
            .unwrap();
        if line.contains("stored row") {
            break;
        }
        assert!(Instant::now() < deadline, "part 2/4 stored no row");
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let objects = part_objects(&s3, "killed");
    assert!(
        !objects.iter().any(|k| k.ends_with("2-of-4.json")),
        "killed before its marker: {objects:?}"
    );

    // The finish refuses while part 2 is missing, and names it.
    let refused = run(&s3, &["import", "--finish", "-o", &volume], &[]);
    assert!(!refused.status.success());
    let e = String::from_utf8_lossy(&refused.stderr);
    assert!(e.contains("part 2/4 has not finished"), "{e}");
    assert!(isovox_server::store::remote::read_head(&volume_bucket(&s3, "killed")).is_err());

    // Run again: it resumes from the row it stored.
    let (stdout, stderr) = ok(&s3, &import_args(&input, &volume, &["--part", "2/4"]), &[]);
    assert!(
        stderr.contains("resuming: 1 stored by an earlier run"),
        "{stderr}"
    );
    assert!(stdout.contains("(1 from an earlier run)"), "{stdout}");
    // Run once more: skipped.
    let (stdout, stderr) = ok(&s3, &import_args(&input, &volume, &["--part", "2/4"]), &[]);
    assert!(
        stderr.contains("had finished already") && stderr.contains("skipped"),
        "{stderr}"
    );
    assert!(stdout.contains("already done"), "{stdout}");

    ok(&s3, &["import", "--finish", "-o", &volume], &[]);
    assert_same_levels(&levels(&s3, &volume, dir.path(), "killed"), &expected);
}

#[test]
fn the_finish_refuses_missing_parts_and_parts_of_another_volume() {
    let s3 = S3::start("split-refuse");
    let dir = tempfile::tempdir().unwrap();
    let input = zarr_input(dir.path());
    let volume = format!("{}/mixed", s3.url());

    let none = run(&s3, &["import", "--finish", "-o", &volume], &[]);
    assert!(!none.status.success());
    let e = String::from_utf8_lossy(&none.stderr);
    assert!(e.contains("no part has finished"), "{e}");

    // Part 0 of 3 with bricks of 16, part 2 of 3 with bricks of 32; part 1 never ran.
    ok(&s3, &import_args(&input, &volume, &["--part", "0/3"]), &[]);
    let mut other = import_args(&input, &volume, &["--part", "2/3"]);
    other[5] = "32";
    ok(&s3, &other, &[]);
    let missing = run(&s3, &["import", "--finish", "-o", &volume], &[]);
    assert!(!missing.status.success());
    let e = String::from_utf8_lossy(&missing.stderr);
    assert!(
        e.contains("part 1/3 has not finished") && e.contains("parts/1-of-3.json"),
        "{e}"
    );

    ok(&s3, &import_args(&input, &volume, &["--part", "1/3"]), &[]);
    let mismatch = run(&s3, &["import", "--finish", "-o", &volume], &[]);
    assert!(!mismatch.status.success());
    let e = String::from_utf8_lossy(&mismatch.stderr);
    assert!(
        e.contains("part 2/3 is of another volume than part 0/3")
            && e.contains("brick 32")
            && e.contains("brick 16"),
        "{e}"
    );
    assert!(isovox_server::store::remote::read_head(&volume_bucket(&s3, "mixed")).is_err());

    // A part run again with other options than its marker's is refused too.
    let redo = run(
        &s3,
        &other[..other.len() - 2]
            .iter()
            .copied()
            .chain(["--part", "0/3"])
            .collect::<Vec<_>>(),
        &[],
    );
    assert!(!redo.status.success());
    let e = String::from_utf8_lossy(&redo.stderr);
    assert!(
        e.contains("part 0/3 was finished for another volume"),
        "{e}"
    );

    // Bad arguments are errors, not panics.
    for (args, says) in [
        (
            vec!["import", "--finish", "-o", "local.vod"],
            "object store",
        ),
        (
            vec!["import", input.0.as_str(), "-o", &volume, "--part", "3/3"],
            "0 to 2",
        ),
        (
            vec!["import", input.0.as_str(), "-o", &volume, "--part", "x"],
            "I/N",
        ),
        (
            vec!["import", input.0.as_str(), "-o", &volume, "--parts", "3"],
            "goes with --finish",
        ),
        (
            vec!["import", input.0.as_str(), "--finish", "-o", &volume],
            "cannot be used with '--finish'",
        ),
    ] {
        let out = run(&s3, &args, &[]);
        assert!(!out.status.success(), "{args:?}");
        let e = String::from_utf8_lossy(&out.stderr);
        assert!(e.contains(says) && !e.contains("panicked"), "{args:?}: {e}");
    }
}

#[test]
fn a_segment_above_the_threshold_goes_up_as_a_multipart_upload() {
    let s3 = S3::start("split-multipart");
    let dir = tempfile::tempdir().unwrap();
    // 192^3 voxels of noise, stored without compression: level 0 alone is 7 MB, so with a
    // threshold of 5 MiB (S3's smallest part) the segment goes up in two parts.
    let dims = [192usize; 3];
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let voxels: Vec<u8> = (0..dims.iter().product::<usize>())
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 56) as u8
        })
        .collect();
    let raw = dir.path().join("noise.raw");
    std::fs::write(&raw, &voxels).unwrap();
    let volume = format!("{}/noise", s3.url());
    let args = [
        "import",
        raw.to_str().unwrap(),
        "--dims",
        "192,192,192",
        "--type",
        "u8",
        "--codec",
        "none",
        "-o",
        &volume,
    ];
    let (stdout, _) = ok(&s3, &args, &[("ISOVOX_MULTIPART_BYTES", "5242880")]);
    assert!(stdout.contains("a multipart upload of 2 parts"), "{stdout}");
    let bucket = volume_bucket(&s3, "noise");
    let segments = bucket.list("seg").unwrap();
    assert_eq!(segments.len(), 1);
    let got = bucket.get_if_changed(&segments[0].key, None).unwrap();
    let isovox_server::store::remote::Conditional::Done(Some(bytes), etag) = got else {
        panic!("the segment reads back");
    };
    // S3 names a multipart object's ETag after its parts: "<md5 of the parts' md5s>-2".
    assert!(etag.trim_matches('"').ends_with("-2"), "ETag {etag}");
    assert!(bytes.len() > 7 << 20, "{} bytes", bytes.len());

    // It reads back equal: level 0 is the input; level 1 is what the same import into a local
    // file gives.
    let back = dir.path().join("back.raw");
    ok(&s3, &["export", &volume, "-o", back.to_str().unwrap()], &[]);
    assert!(
        std::fs::read(&back).unwrap() == voxels,
        "level 0 reads back as imported"
    );
    let local = dir.path().join("noise.vod");
    let mut local_args = args.to_vec();
    let last = local_args.len() - 1;
    local_args[last] = local.to_str().unwrap();
    ok(&s3, &local_args, &[]);
    let (a, b) = (dir.path().join("a1.raw"), dir.path().join("b1.raw"));
    ok(
        &s3,
        &["export", &volume, "--level", "1", "-o", a.to_str().unwrap()],
        &[],
    );
    ok(
        &s3,
        &[
            "export",
            local.to_str().unwrap(),
            "--level",
            "1",
            "-o",
            b.to_str().unwrap(),
        ],
        &[],
    );
    assert!(std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap());
    // The segment is the local file up to its commit record (which holds the commit's time).
    let file = std::fs::read(&local).unwrap();
    let (head, _) = isovox_server::store::remote::read_head(&bucket).unwrap();
    let commit = head.commit as usize;
    assert_eq!(file.len(), bytes.len());
    assert!(bytes[..commit] == file[..commit]);

    // The noise imported again as volume `name` with a multipart threshold of `threshold`.
    let import_as = |name: &str, threshold: &str| {
        let output = format!("{}/{name}", s3.url());
        let args = [
            "import",
            raw.to_str().unwrap(),
            "--dims",
            "192,192,192",
            "--type",
            "u8",
            "-o",
            &output,
        ];
        run(&s3, &args, &[("ISOVOX_MULTIPART_BYTES", threshold)])
    };
    // Below the threshold: one PUT.
    let out = import_as("small", "67108864");
    assert!(out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("(one PUT)"), "{stdout}");

    // Bytes in memory (a part's brick rows) go up the same way: 11 MB in three parts.
    std::env::set_var("ISOVOX_MULTIPART_BYTES", "5242880");
    let body: Vec<u8> = voxels.iter().cycle().take(11 << 20).copied().collect();
    let parts = bucket
        .put_large("parts/big", bytes::Bytes::from(body.clone()))
        .unwrap();
    // (Set for this process only as long as needed: the other tests' processes inherit it.)
    std::env::remove_var("ISOVOX_MULTIPART_BYTES");
    assert_eq!(parts, 3);
    let got = bucket.get_if_changed("parts/big", None).unwrap();
    let isovox_server::store::remote::Conditional::Done(Some(back), etag) = got else {
        panic!("the object reads back");
    };
    assert!(etag.trim_matches('"').ends_with("-3"), "ETag {etag}");
    assert!(back.as_ref() == body.as_slice());

    // A threshold that is not a number is an error, not the default.
    let out = import_as("badly", "64MiB");
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("ISOVOX_MULTIPART_BYTES=\"64MiB\""), "{e}");
}

/// The validator `.ci/run` installs: kubernetes-validate (PyPI, pinned) in `target/k8s-venv`.
fn kubernetes_validate() -> PathBuf {
    let bin = std::env::var("ISOVOX_K8S_VALIDATE")
        .map(PathBuf::from)
        .unwrap_or_else(|_| workspace().join("target/k8s-venv/bin/kubernetes-validate"));
    assert!(
        bin.exists(),
        "no kubernetes-validate at {} (run .ci/run, which installs it, or set ISOVOX_K8S_VALIDATE)",
        bin.display()
    );
    bin
}

#[test]
fn the_kubernetes_manifests_validate_against_the_schemas() {
    let bin = kubernetes_validate();
    let k8s = workspace().join("docker/k8s");
    let mut manifests: Vec<PathBuf> = std::fs::read_dir(&k8s)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml"))
        .collect();
    manifests.sort();
    assert_eq!(manifests.len(), 3, "{manifests:?}");
    // Strict: a field the schema does not know is an error. Checked against the newest
    // Kubernetes the validator knows and an older one still in support.
    for version in ["1.37.0", "1.31.0"] {
        let out = Command::new(&bin)
            .args(["--strict", "-k", version])
            .args(&manifests)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned()
            + &String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "Kubernetes {version}: {text}");
        assert_eq!(text.matches(" passed ").count(), 3, "{text}");
    }
    // The parts Job is what the docs say: Indexed, N completions, --part INDEX/N.
    let parts = std::fs::read_to_string(k8s.join("import-parts.yaml")).unwrap();
    assert!(parts.contains("completionMode: Indexed"));
    assert!(parts.contains("completions: 8") && parts.contains("\"$(PART_INDEX)/8\""));
    assert!(parts.contains("batch.kubernetes.io/job-completion-index"));

    // The validator does reject a broken manifest (a misspelt field, a wrong type).
    let dir = tempfile::tempdir().unwrap();
    for (from, to) in [
        (
            "completionMode: Indexed",
            "completionMode: Indexed\n  completionz: 3",
        ),
        ("parallelism: 4", "parallelism: four"),
    ] {
        let bad = dir.path().join("bad.yaml");
        std::fs::write(&bad, parts.replacen(from, to, 1)).unwrap();
        let out = Command::new(&bin)
            .arg("--strict")
            .arg(&bad)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{to:?} is refused");
    }
}
