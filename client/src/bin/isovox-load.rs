//! `isovox-load`: simulated viewers and editors against an Isovox server (placeholder until the
//! load tester lands).

fn main() {
    eprintln!("isovox-load: not built yet");
    std::process::exit(2);
}
