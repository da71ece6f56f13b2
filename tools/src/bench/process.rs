//! An `isovox serve` child process for the benchmarks that measure the server as users run it:
//! its memory and threads are its own, read from `/proc/PID/status`.

use anyhow::Context;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};

/// A running `isovox serve --addr 127.0.0.1:0`, killed when dropped.
#[derive(Debug)]
pub struct ServeProcess {
    child: Child,
    /// `http://ADDR`.
    pub base: String,
    log: Arc<Mutex<Vec<String>>>,
}

impl ServeProcess {
    /// Runs `exe serve --addr 127.0.0.1:0 --data DATA` with `envs` set (`ISOVOX_*` variables
    /// rather than flags, which an older build would refuse) and waits for the line announcing
    /// its address; its standard error is drained and kept from then on.
    ///
    /// # Errors
    /// It cannot start, or exits before it listens.
    pub fn start(exe: &Path, data: &Path, envs: &[(&str, String)]) -> anyhow::Result<ServeProcess> {
        let mut child = Command::new(exe)
            .args(["serve", "--addr", "127.0.0.1:0", "--data"])
            .arg(data)
            .envs(envs.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .with_context(|| format!("cannot start {} serve", exe.display()))?;
        let stderr = child.stderr.take().context("no stderr")?;
        let mut server = ServeProcess {
            child,
            base: String::new(),
            log: Arc::default(),
        };
        let mut lines = BufReader::new(stderr).lines();
        server.base = loop {
            let line = lines
                .next()
                .context("the server exited before listening")??;
            let at = line.find("http://");
            server
                .log
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(line.clone());
            if let Some(at) = at {
                let rest = &line[at..];
                break rest.split("/v1").next().unwrap_or(rest).trim().to_string();
            }
        };
        let log = server.log.clone();
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                log.lock().unwrap_or_else(|e| e.into_inner()).push(line);
            }
        });
        Ok(server)
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The first line of its standard error that starts with `prefix`.
    pub fn log_line(&self, prefix: &str) -> Option<String> {
        let log = self.log.lock().unwrap_or_else(|e| e.into_inner());
        log.iter().find(|l| l.starts_with(prefix)).cloned()
    }

    /// A field of its `/proc/PID/status` ([`proc_status`]).
    pub fn status(&self, field: &str) -> Option<u64> {
        proc_status(self.pid(), field)
    }
}

/// A field of `/proc/PID/status` (`VmRSS`, `VmHWM`, `Threads`...) in its unit (KiB for
/// memory), if the process is running.
pub fn proc_status(pid: u32, field: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
