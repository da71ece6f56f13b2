//! A run's report as Markdown tables: one function per section.

use super::report::plural;
use super::LoadReport;
use std::fmt::Write;

impl LoadReport {
    /// The report as Markdown tables.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        self.write_heading(&mut s);
        self.write_routes(&mut s);
        self.write_errors(&mut s);
        if self.edits.editors > 0 {
            self.write_edits(&mut s);
            self.write_notifications(&mut s);
        }
        self.write_presence(&mut s);
        self.write_streamers(&mut s);
        s
    }

    /// What ran, against what, for how long, with which streamer settings.
    fn write_heading(&self, s: &mut String) {
        let _ = writeln!(
            s,
            "## isovox-load: {} viewer{} + {} editor{}, {} along {} paths over `{}`, {:.1} s (asked {} s)\n",
            self.viewers,
            plural(self.viewers),
            self.editors,
            plural(self.editors),
            self.tiles,
            self.path,
            self.volume,
            self.elapsed_s,
            self.duration_s
        );
        let radii: Vec<String> = self.radii.iter().map(|r| format!("{r:.0}")).collect();
        let _ = writeln!(
            s,
            "Server {}, versions {} -> {}. Streamers: radii {}, at most {} requests in flight (halved \
             on a 503; {} in all at the end), {} MiB cache each. Latency: time to the response's \
             headers, every attempt.\n",
            self.url,
            self.version_start,
            self.version_end,
            radii.join(", "),
            self.max_in_flight,
            self.streamers.in_flight_limit_at_end,
            self.cache_bytes >> 20
        );
    }

    /// The routes' table, with the sum over all of them last.
    fn write_routes(&self, s: &mut String) {
        let _ = writeln!(
            s,
            "| route | requests | 2xx | 304 | retried | errors | MiB | req/s | MiB/s | p50 ms | p90 ms | p99 ms | max ms |"
        );
        let _ = writeln!(
            s,
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        for r in self.routes.iter().chain(std::iter::once(&self.total)) {
            let l = &r.latency_ms;
            let name = if r.route == "all" {
                "**all**".to_string()
            } else {
                format!("`{}`", r.route)
            };
            let _ = writeln!(
                s,
                "| {name} | {} | {} | {} | {} | {} | {:.2} | {:.0} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} |",
                r.requests,
                r.ok,
                r.not_modified,
                r.retried,
                r.errors,
                r.bytes as f64 / f64::from(1u32 << 20),
                r.requests_per_s,
                r.mib_per_s,
                l.p50,
                l.p90,
                l.p99,
                l.max
            );
        }
        let _ = writeln!(s);
    }

    /// The count of errors, and their table when there are any.
    fn write_errors(&self, s: &mut String) {
        if self.errors.is_empty() {
            let _ = writeln!(s, "Errors: **0**.\n");
        } else {
            let _ = writeln!(s, "Errors: **{}**.\n", self.errors_total);
            let _ = writeln!(
                s,
                "| source | kind | count | first at | last at |\n|---|---|---:|---:|---:|"
            );
            let at = |t: Option<f64>| t.map_or(String::new(), |t| format!("{t:.1} s"));
            for e in &self.errors {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} |",
                    e.source,
                    e.kind,
                    e.count,
                    at(e.first_s),
                    at(e.last_s)
                );
            }
            let _ = writeln!(s);
        }
    }

    /// The editors' table.
    fn write_edits(&self, s: &mut String) {
        let e = &self.edits;
        let l = &e.latency_ms;
        let _ = writeln!(
            s,
            "| edits | attempted | acknowledged | failed | carves | additions | per s | p50 ms | p90 ms | p99 ms | max ms |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        let _ = writeln!(
            s,
            "| {} editor{} at {}/s | {} | {} | {} | {} | {} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} |\n",
            e.editors,
            plural(e.editors),
            e.rate_per_editor,
            e.attempted,
            e.acknowledged,
            e.failed,
            e.carves,
            e.additions,
            e.acknowledged_per_s,
            l.p50,
            l.p90,
            l.p99,
            l.max
        );
        if e.undos > 0 {
            let u = &e.undo_latency_ms;
            let _ = writeln!(
                s,
                "Undos of their own edits: {} acknowledged, {} later edits applied again; latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms.\n",
                e.undos, e.replayed, u.p50, u.p99, u.max
            );
        }
    }

    /// The edit-to-notification table: from the acknowledgement, and from sending the edit.
    fn write_notifications(&self, s: &mut String) {
        let n = &self.notifications;
        let l = &n.latency_ms;
        let _ = writeln!(
            s,
            "| edit to notification | expected | seen | missing | before ack | resyncs | reconnects | p50 ms | p90 ms | p99 ms | max ms |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        let _ = writeln!(
            s,
            "| {} subscriber{}, from the ack | {} | {} | {} | {} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} |",
            n.subscribers,
            plural(n.subscribers),
            n.expected,
            n.seen,
            n.missing,
            n.before_ack,
            n.resyncs,
            n.reconnects,
            l.p50,
            l.p90,
            l.p99,
            l.max
        );
        let l = &n.from_send_ms;
        let _ = writeln!(
            s,
            "| from sending the edit | | | | | | | {:.2} | {:.2} | {:.2} | {:.2} |\n",
            l.p50, l.p90, l.p99, l.max
        );
    }

    /// The streamers' table, tiles by level, and the streamers' failures.
    fn write_presence(&self, s: &mut String) {
        let Some(p) = &self.presence else {
            return;
        };
        let _ = writeln!(
            s,
            "### Presence\n\n| sent | accepted | 429 | failed | arrivals at subscribers | per accepted message | send to arrival p50 ms | p99 ms |\n|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {:.2} | {:.2} | {:.2} |\n",
            p.sent,
            p.accepted,
            p.limited,
            p.failed,
            p.delivered,
            p.fan_out,
            p.delay_p50_ms,
            p.delay_p99_ms
        );
    }

    fn write_streamers(&self, s: &mut String) {
        let t = &self.streamers;
        let _ = writeln!(
            s,
            "| streamers | tiles ready | MiB ready | dropped | stale | stale refetches | cache hits | cache misses | hit rate | resident at end | versions at end |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|");
        let _ = writeln!(
            s,
            "| {} | {} | {:.2} | {} | {} | {} | {} | {} | {:.1}% | {} | {}..{} |\n",
            t.streamers,
            t.tiles_ready,
            t.ready_bytes as f64 / f64::from(1u32 << 20),
            t.dropped,
            t.stale,
            t.stale_refetches,
            t.cache_hits,
            t.cache_misses,
            t.cache_hit_rate * 100.0,
            t.resident_at_end,
            t.min_version,
            t.max_version
        );
        let levels: Vec<String> = t
            .ready_by_level
            .iter()
            .enumerate()
            .map(|(l, n)| format!("L{l} {n}"))
            .collect();
        let _ = writeln!(s, "Tiles ready by level: {}.", levels.join(", "));
        let f = &t.first_tile_ms;
        let _ = writeln!(
            s,
            "\nGrid regions asked: {} ({} for tiles an edit invalidated, {} dropped before their answer was used); tiles skipped (no surface): {}.\n\nFirst tile per viewer (ms, from its start): p50 {:.0}, p99 {:.0}, max {:.0} ({} viewers; {} got none).",
            t.grid_requests,
            t.edit_grid_requests,
            t.grid_aborted,
            t.skipped,
            f.p50,
            f.p99,
            f.max,
            f.samples,
            t.without_tile
        );
        let d = &t.first_drawn_ms;
        let _ = writeln!(
            s,
            "First tile that draws per viewer (a mesh with a triangle, a brick holding the surface; ms): p50 {:.0}, p99 {:.0}, max {:.0} ({} viewers; {} got none).",
            d.p50, d.p99, d.max, d.samples, t.without_drawn
        );
        if t.failed_to_start > 0 || t.never_started > 0 {
            let _ = writeln!(
                s,
                "\n{} streamers failed to start; the ramp-up never reached {} users.",
                t.failed_to_start, t.never_started
            );
        }
        if !t.error_samples.is_empty() {
            let _ = writeln!(s, "\nStreamer errors (first {}):", t.error_samples.len());
            for m in &t.error_samples {
                let _ = writeln!(s, "- {m}");
            }
        }
    }
}
