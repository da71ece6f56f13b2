//! A real `isovox serve` process for the tests that need one: started on an ephemeral port,
//! optionally under a file-descriptor limit, its standard error drained (a full pipe would
//! block the server) and kept for failure messages, its memory and threads read from
//! `/proc`, killed (SIGKILL) when dropped so a failing test leaves no server behind.
//!
//! `ISOVOX_TEST_BIN=PATH` runs the tests against another build of `isovox` (an older one, to
//! see a test fail before a fix: configure such servers through `ISOVOX_*` variables, which an
//! older build ignores, rather than flags, which it refuses).

#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// The environment variables `isovox serve` reads: removed from the child's environment so a
/// developer's shell cannot change what a test runs.
const SERVE_ENV: &[&str] = &[
    "ISOVOX_WRITE_TOKEN",
    "ISOVOX_TOKEN_FILE",
    "ISOVOX_PRIVATE_READS",
    "ISOVOX_OIDC_ISSUER",
    "ISOVOX_OIDC_AUDIENCE",
    "ISOVOX_OIDC_ROLES_CLAIM",
    "ISOVOX_OIDC_JWKS",
    "ISOVOX_OIDC_CLIENT_ID",
    "ISOVOX_OIDC_REFRESH_INTERVAL",
    "ISOVOX_EDIT_RATE",
    "ISOVOX_EDIT_QUEUE",
    "ISOVOX_EDIT_GROUP",
    "ISOVOX_MAX_EDIT_VOXELS",
    "ISOVOX_EDIT_TIMEOUT",
    "ISOVOX_SHUTDOWN_GRACE",
    "ISOVOX_CPU_QUEUE",
    "ISOVOX_RESPONSE_MEMORY_MB",
    "ISOVOX_MAX_CONNECTIONS",
    "ISOVOX_HEADER_TIMEOUT",
    "ISOVOX_IDLE_TIMEOUT",
];

/// A running `isovox serve`.
pub(crate) struct ServerProcess {
    child: Child,
    /// `host:port` the server announced.
    pub(crate) addr: String,
    /// The line that announced it ("isovox serving NAMES on http://ADDR/v1/volumes").
    pub(crate) announced: String,
    log: Arc<Mutex<Vec<String>>>,
    drain: Option<JoinHandle<()>>,
}

impl ServerProcess {
    /// Runs `isovox serve --addr 127.0.0.1:0 ARGS` with `envs` set, and waits (up to 60 s) for
    /// its "isovox serving ... on http://ADDR/..." line.
    pub(crate) fn start(args: &[&std::ffi::OsStr], envs: &[(&str, &str)]) -> ServerProcess {
        ServerProcess::launch("127.0.0.1:0", None, args, envs)
    }

    /// [`ServerProcess::start`] listening on `addr` (`HOST:PORT`).
    pub(crate) fn start_on(
        addr: &str,
        args: &[&std::ffi::OsStr],
        envs: &[(&str, &str)],
    ) -> ServerProcess {
        ServerProcess::launch(addr, None, args, envs)
    }

    /// As [`ServerProcess::start`], under a limit of `fd_limit` open files (soft and hard, set
    /// by the shell that starts the server) when given.
    pub(crate) fn start_limited(
        fd_limit: Option<u32>,
        args: &[&std::ffi::OsStr],
        envs: &[(&str, &str)],
    ) -> ServerProcess {
        ServerProcess::launch("127.0.0.1:0", fd_limit, args, envs)
    }

    fn launch(
        addr: &str,
        fd_limit: Option<u32>,
        args: &[&std::ffi::OsStr],
        envs: &[(&str, &str)],
    ) -> ServerProcess {
        let mut command = match fd_limit {
            None => Command::new(isovox()),
            Some(n) => {
                let mut sh = Command::new("sh");
                sh.arg("-c")
                    .arg(format!("ulimit -n {n} && exec \"$0\" \"$@\""))
                    .arg(isovox());
                sh
            }
        };
        command.args(["serve", "--addr", addr]).args(args);
        for name in SERVE_ENV {
            command.env_remove(name);
        }
        command.envs(envs.iter().copied());
        let mut child = command
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("the isovox binary starts");
        let stderr = child.stderr.take().expect("stderr is piped");
        let log = Arc::new(Mutex::new(Vec::new()));
        let (announce, announced) = mpsc::channel();
        let drain = {
            let log = Arc::clone(&log);
            std::thread::spawn(move || {
                let mut announce = Some(announce);
                for line in BufReader::new(stderr).lines() {
                    let Ok(line) = line else { break };
                    if line.contains("isovox serving") {
                        if let Some(tx) = announce.take() {
                            let _ = tx.send(line.clone());
                        }
                    }
                    log.lock().unwrap().push(line);
                }
            })
        };
        let mut server = ServerProcess {
            child,
            addr: String::new(),
            announced: String::new(),
            log,
            drain: Some(drain),
        };
        let line = match announced.recv_timeout(Duration::from_secs(60)) {
            Ok(line) => line,
            Err(_) => {
                let status = server.child.try_wait().ok().flatten();
                panic!(
                    "the server did not announce its address; exit {status:?}; its stderr:\n{}",
                    server.stop()
                )
            }
        };
        server.addr = address_in(&line)
            .unwrap_or_else(|| panic!("no address in {line:?}"))
            .to_string();
        server.announced = line;
        server
    }

    /// `http://ADDR` followed by `path`.
    pub(crate) fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// The address, parsed.
    pub(crate) fn socket_addr(&self) -> std::net::SocketAddr {
        self.addr.parse().expect("the announced address parses")
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Its memory and threads now, as `/proc/PID/status` says.
    pub(crate) fn status(&self) -> ProcStatus {
        let text = std::fs::read_to_string(format!("/proc/{}/status", self.pid()))
            .expect("the server is running");
        let field = |name: &str| -> u64 {
            let line = text
                .lines()
                .find_map(|l| l.strip_prefix(name))
                .unwrap_or_else(|| panic!("no {name} in /proc/PID/status"));
            let n: u64 = line
                .split_whitespace()
                .next()
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("{name}{line}"));
            if line.ends_with("kB") {
                n << 10
            } else {
                n
            }
        };
        ProcStatus {
            rss: field("VmRSS:"),
            hwm: field("VmHWM:"),
            threads: field("Threads:"),
        }
    }

    /// The last `lines` lines the server wrote to standard error.
    pub(crate) fn log_tail(&self, lines: usize) -> String {
        let log = self.log.lock().unwrap();
        log[log.len().saturating_sub(lines)..].join("\n")
    }

    /// Everything the server wrote to standard error so far.
    pub(crate) fn log(&self) -> String {
        self.log.lock().unwrap().join("\n")
    }

    /// Sends SIGTERM (a graceful shutdown) and waits up to `hangs` for the server to exit:
    /// its exit status, or `None` if it was still running then (it is killed afterwards).
    pub(crate) fn terminate(&mut self, hangs: Duration) -> Option<std::process::ExitStatus> {
        let sent = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .expect("kill runs");
        assert!(sent.success(), "kill -TERM failed: {sent}");
        let start = std::time::Instant::now();
        while start.elapsed() < hangs {
            if let Some(status) = self.child.try_wait().expect("the server can be waited for") {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        None
    }

    /// Kills the server (SIGKILL), waits for it and for its standard error to end, and returns
    /// everything it wrote there.
    pub(crate) fn stop(&mut self) -> String {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(drain) = self.drain.take() {
            let _ = drain.join();
        }
        self.log()
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What `/proc/PID/status` says of a process's memory and threads.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ProcStatus {
    /// Resident memory now, bytes.
    pub(crate) rss: u64,
    /// The most resident memory so far, bytes.
    pub(crate) hwm: u64,
    pub(crate) threads: u64,
}

/// The `isovox` binary under test: this build's, or `ISOVOX_TEST_BIN`.
pub(crate) fn isovox() -> std::ffi::OsString {
    std::env::var_os("ISOVOX_TEST_BIN").unwrap_or_else(|| env!("CARGO_BIN_EXE_isovox").into())
}

/// Runs `isovox ARGS` to completion; panics with its output when it fails.
pub(crate) fn run_isovox(args: &[&str]) {
    let out = Command::new(isovox())
        .args(args)
        .output()
        .expect("the isovox binary starts");
    assert!(out.status.success(), "isovox {args:?}: {out:?}");
}

/// `isovox generate world` of `dims` ("X,Y,Z") as `dir/world.vod`.
pub(crate) fn generate_world(dir: &std::path::Path, dims: &str) {
    let out = dir.join("world.vod");
    let out = out.to_str().expect("a UTF-8 temporary path");
    run_isovox(&["generate", "world", "-o", out, "--dims", dims]);
}

/// `ADDR` in "isovox serving w on http://ADDR/v1/volumes" (or https).
fn address_in(line: &str) -> Option<&str> {
    let rest = &line[line.find("://")? + "://".len()..];
    Some(&rest[..rest.find('/').unwrap_or(rest.len())])
}
