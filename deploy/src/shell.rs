//! Words for a POSIX shell: what `ctxrace sweep --emit` writes into the commands and scripts it
//! prints.

/// Whether `c` needs no shell quoting.
pub fn is_plain(c: char) -> bool {
    c.is_ascii_alphanumeric() || "-_./:=,+@%".contains(c)
}

/// `s` quoted for a POSIX shell where it needs to be.
pub fn shell_quote(s: &str) -> String {
    if !s.is_empty() && s.chars().all(is_plain) {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', "'\\''"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shell_quoting_keeps_plain_words_and_quotes_the_rest() {
        assert_eq!(shell_quote("runs/a-1r-s0"), "runs/a-1r-s0");
        assert_eq!(shell_quote("my runs"), "'my runs'");
        assert_eq!(shell_quote("it's"), "'it'\\''s'");
    }
}
