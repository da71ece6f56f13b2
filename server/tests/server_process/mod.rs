//! A real `isovox serve` process for the tests that need one: started on an ephemeral port,
//! its standard error drained (a full pipe would block the server) and kept for failure
//! messages, killed (SIGKILL) when dropped so a failing test leaves no server behind.

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
    "ISOVOX_EDIT_RATE",
    "ISOVOX_EDIT_QUEUE",
    "ISOVOX_EDIT_GROUP",
    "ISOVOX_MAX_EDIT_VOXELS",
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
        let mut command = Command::new(env!("CARGO_BIN_EXE_isovox"));
        command.args(["serve", "--addr", "127.0.0.1:0"]).args(args);
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

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
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

/// `ADDR` in "isovox serving w on http://ADDR/v1/volumes".
fn address_in(line: &str) -> Option<&str> {
    let rest = &line[line.find("http://")? + "http://".len()..];
    Some(&rest[..rest.find('/').unwrap_or(rest.len())])
}
