//! What a command shows as it goes: progress bars.

use indicatif::{ProgressBar, ProgressStyle};

/// A progress bar over `len` `unit`s with their rate and, in its message, live figures.
pub fn progress_bar(len: u64, unit: &str) -> ProgressBar {
    let template =
        format!("{{elapsed_precise}} [{{bar:30}}] {{pos}}/{{len}} {unit} ({{per_sec}}) {{msg}}");
    let bar = ProgressBar::new(len);
    match ProgressStyle::with_template(&template) {
        Ok(style) => bar.with_style(style),
        Err(_) => bar,
    }
}
