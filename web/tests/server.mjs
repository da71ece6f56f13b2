// A real `isovox serve` as a child process for the browser tests and the benchmark: on a port
// the kernel picks (or a given one, to restart on the same address), killed with SIGKILL.

import { spawn } from "node:child_process";
import { readFileSync } from "node:fs";
import { join } from "node:path";

/**
 * Starts `bin serve --data dataDir` and resolves when it announces its address (the demo world
 * is generated first when the directory holds no volume).
 */
export function startServer(bin, dataDir, { addr = "127.0.0.1:0", extraArgs = [] } = {}) {
  const child = spawn(bin, ["serve", "--data", dataDir, "--addr", addr, ...extraArgs], {
    stdio: ["ignore", "ignore", "pipe"],
    env: { ...process.env, RUST_LOG: process.env.RUST_LOG ?? "warn" },
  });
  const log = [];
  return new Promise((resolve, reject) => {
    let announced = false;
    let pending = "";
    child.stderr.setEncoding("utf8");
    child.stderr.on("data", (chunk) => {
      pending += chunk;
      const lines = pending.split("\n");
      pending = lines.pop() ?? "";
      for (const line of lines) {
        log.push(line);
        const m = /isovox serving .* on (https?):\/\/([^/\s]+)\//.exec(line);
        if (m && !announced) {
          announced = true;
          const base = `${m[1]}://${m[2]}`;
          resolve({
            base,
            addr: m[2],
            child,
            log,
            kill: () =>
              new Promise((done) => {
                if (child.exitCode !== null || child.signalCode !== null) return done();
                child.once("exit", () => done());
                child.kill("SIGKILL");
              }),
          });
        }
      }
    });
    child.once("exit", (code, signal) => {
      if (!announced) {
        reject(new Error(`isovox serve exited (${code ?? signal}) before serving:\n${log.join("\n")}`));
      }
    });
  });
}

/** The write token the server created in `dataDir/tokens` on its first start. */
export function demoToken(dataDir) {
  const line = readFileSync(join(dataDir, "tokens"), "utf8")
    .split("\n")
    .find((l) => l.startsWith("demo "));
  if (!line) throw new Error(`no demo token in ${dataDir}/tokens`);
  return line.split(/\s+/)[1];
}
