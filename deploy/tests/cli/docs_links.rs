//! The documentation's relative links: every link in README.md, ARCHITECTURE.md and
//! docs/**/*.md names a file or folder that exists, and an `#anchor` into a markdown file names
//! one of its headings. Every guide under docs/guides/ is linked from the README.
//!
//! Inline links and images (`[text](target)`, `![alt](target)`) are checked; links inside fenced
//! code blocks and code spans are not links; URLs and e-mail addresses are not checked.

use std::collections::{HashMap, HashSet};
use std::fs;
use std::path::{Path, PathBuf};

/// The repository root: the folder above this package's (`deploy/`).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the package folder has a parent")
        .to_path_buf()
}

/// Reads a document; a missing or unreadable one fails the test, naming it.
fn read(path: &Path) -> String {
    fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// The markdown files whose links are checked: README.md, ARCHITECTURE.md and docs/**/*.md.
/// Fails when one of the two top files is missing or docs/ holds no markdown file.
fn documents() -> Vec<PathBuf> {
    let root = root();
    let mut docs = vec![root.join("README.md"), root.join("ARCHITECTURE.md")];
    for d in &docs {
        assert!(d.is_file(), "{} is missing", d.display());
    }
    let mut under = Vec::new();
    markdown_under(&root.join("docs"), &mut under);
    assert!(
        !under.is_empty(),
        "no markdown file under {}",
        root.join("docs").display()
    );
    docs.extend(under);
    docs
}

/// Appends the markdown files under `dir`, recursively, in a stable order.
fn markdown_under(dir: &Path, out: &mut Vec<PathBuf>) {
    let entries =
        fs::read_dir(dir).unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()));
    let mut paths: Vec<PathBuf> = entries
        .map(|e| e.expect("a readable folder entry").path())
        .collect();
    paths.sort();
    for p in paths {
        if p.is_dir() {
            markdown_under(&p, out);
        } else if p.extension().is_some_and(|x| x == "md") {
            out.push(p);
        }
    }
}

/// A link of a document: its target as written and the line it is on (from 1).
#[derive(Debug, PartialEq)]
struct Link {
    /// The target as written, without angle brackets or title.
    target: String,
    /// The line of the `](` that opens the target.
    line: usize,
}

/// The text with every fenced code block's lines blanked (line breaks kept).
fn without_fences(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut fence: Option<&str> = None;
    for line in text.split_inclusive('\n') {
        let t = line.trim_start();
        let marker = if t.starts_with("```") {
            Some("```")
        } else if t.starts_with("~~~") {
            Some("~~~")
        } else {
            None
        };
        let blank = match (fence, marker) {
            (None, Some(m)) => {
                fence = Some(m);
                true
            }
            (Some(f), Some(m)) if f == m => {
                fence = None;
                true
            }
            (Some(_), _) => true,
            (None, None) => false,
        };
        if blank {
            out.extend(line.chars().filter(|&c| c == '\n'));
        } else {
            out.push_str(line);
        }
    }
    out
}

/// The text with every code span's characters blanked (line breaks kept). A span opens with a
/// run of backticks and closes with a run of the same length in the same paragraph; a run with
/// no partner is text.
fn without_code_spans(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let mut out = chars.clone();
    let run_at = |i: usize| chars[i..].iter().take_while(|&&c| c == '`').count();
    let mut i = 0;
    while i < chars.len() {
        if chars[i] != '`' {
            i += 1;
            continue;
        }
        let n = run_at(i);
        let mut j = i + n;
        let mut close = None;
        while j < chars.len() {
            if chars[j] == '\n'
                && chars[j + 1..]
                    .iter()
                    .take_while(|c| **c != '\n')
                    .all(|c| c.is_whitespace())
            {
                break; // a blank line ends the paragraph
            }
            if chars[j] == '`' {
                let m = run_at(j);
                if m == n {
                    close = Some(j + m);
                    break;
                }
                j += m;
            } else {
                j += 1;
            }
        }
        match close {
            Some(end) => {
                for c in &mut out[i..end] {
                    if *c != '\n' {
                        *c = ' ';
                    }
                }
                i = end;
            }
            None => i += n,
        }
    }
    out.into_iter().collect()
}

/// The target of a link whose `(` has just been read: up to the matching `)`, without angle
/// brackets or a title. None when the parenthesis is not closed on that line.
fn target(rest: &str) -> Option<String> {
    if let Some(inner) = rest.strip_prefix('<') {
        return inner.find('>').map(|end| inner[..end].to_string());
    }
    let mut depth = 0usize;
    for (k, c) in rest.char_indices() {
        match c {
            '(' => depth += 1,
            ')' if depth == 0 => return Some(rest[..k].to_string()),
            ')' => depth -= 1,
            c if c.is_whitespace() => return Some(rest[..k].to_string()),
            _ => {}
        }
    }
    None
}

/// The inline links and images of a markdown text, outside fenced code blocks and code spans.
fn links(text: &str) -> Vec<Link> {
    let text = without_code_spans(&without_fences(text));
    let mut found = Vec::new();
    let mut from = 0;
    while let Some(k) = text[from..].find("](") {
        let at = from + k;
        let line = text[..at].matches('\n').count() + 1;
        if let Some(t) = target(&text[at + 2..]) {
            found.push(Link { target: t, line });
        }
        from = at + 2;
    }
    found
}

/// GitHub's anchor of a heading's text: lower case, letters, digits, `-` and `_` kept, spaces
/// made `-`, everything else dropped.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a markdown text's ATX headings (`## A b` gives `a-b`), outside fenced code
/// blocks; a repeated anchor gets `-1`, `-2`, … as on GitHub.
fn anchors(text: &str) -> HashSet<String> {
    let mut seen: HashMap<String, usize> = HashMap::new();
    let mut out = HashSet::new();
    for line in without_fences(text).lines() {
        let hashes = line.chars().take_while(|&c| c == '#').count();
        if !(1..=6).contains(&hashes) || !line[hashes..].starts_with(' ') {
            continue;
        }
        let base = slug(line[hashes..].trim().trim_end_matches('#'));
        let n = seen.entry(base.clone()).or_insert(0);
        out.insert(if *n == 0 {
            base.clone()
        } else {
            format!("{base}-{n}")
        });
        *n += 1;
    }
    out
}

/// Whether a target leaves the repository: a URL (`scheme:`) or an e-mail address.
fn is_external(target: &str) -> bool {
    match target.find(':') {
        Some(k) => {
            let scheme = &target[..k];
            !scheme.is_empty()
                && scheme
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c))
        }
        None => false,
    }
}

/// A link's path with `%XX` escapes decoded.
fn percent_decoded(path: &str) -> String {
    let bytes = path.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = bytes
            .get(i + 1..i + 3)
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u8::from_str_radix(h, 16).ok());
        match (bytes[i], hex) {
            (b'%', Some(b)) => {
                out.push(b);
                i += 3;
            }
            (b, _) => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// What is wrong with one link of `doc`, if anything: a missing file or folder, or an anchor
/// that names no heading of the markdown file it points into.
fn problem(doc: &Path, link: &Link) -> Option<String> {
    let (path, anchor) = match link.target.split_once('#') {
        Some((p, a)) => (p, Some(a)),
        None => (link.target.as_str(), None),
    };
    let file = if path.is_empty() {
        doc.to_path_buf()
    } else {
        doc.parent()
            .expect("a document lies in a folder")
            .join(percent_decoded(path))
    };
    if !file.exists() {
        return Some(format!("{} does not exist", file.display()));
    }
    let anchor = anchor.filter(|a| !a.is_empty())?;
    if !file.is_file() || file.extension().is_none_or(|x| x != "md") {
        return None;
    }
    let anchor = percent_decoded(anchor);
    if anchors(&read(&file)).contains(&anchor) {
        None
    } else {
        Some(format!(
            "{} has no heading with the anchor #{anchor}",
            file.display()
        ))
    }
}

/// The checked documents' relative links, each with the document it is in.
fn relative_links() -> Vec<(PathBuf, Link)> {
    let mut all = Vec::new();
    for doc in documents() {
        for link in links(&read(&doc)) {
            if !is_external(&link.target) {
                all.push((doc.clone(), link));
            }
        }
    }
    all
}

#[test]
fn every_relative_link_names_an_existing_file_and_heading() {
    let all = relative_links();
    let readme = root().join("README.md");
    assert!(
        all.iter().any(|(d, _)| *d == readme),
        "no relative link found in {}: the link parser or the README is broken",
        readme.display()
    );
    let broken: Vec<String> = all
        .iter()
        .filter_map(|(doc, link)| {
            problem(doc, link)
                .map(|why| format!("{}:{}: ({}): {why}", doc.display(), link.line, link.target))
        })
        .collect();
    assert!(
        broken.is_empty(),
        "{} broken link(s) of {} checked:\n{}",
        broken.len(),
        all.len(),
        broken.join("\n")
    );
}

#[test]
fn every_guide_is_linked_from_the_readme() {
    let root = root();
    let mut guides = Vec::new();
    markdown_under(&root.join("docs/guides"), &mut guides);
    assert!(
        !guides.is_empty(),
        "no guide under {}",
        root.join("docs/guides").display()
    );
    let readme = root.join("README.md");
    let linked: HashSet<PathBuf> = links(&read(&readme))
        .iter()
        .filter(|l| !is_external(&l.target))
        .map(|l| root.join(percent_decoded(l.target.split('#').next().unwrap_or(""))))
        .collect();
    let unlinked: Vec<String> = guides
        .iter()
        .filter(|g| !linked.contains(*g))
        .map(|g| g.display().to_string())
        .collect();
    assert!(
        unlinked.is_empty(),
        "guides not linked from {}:\n{}",
        readme.display(),
        unlinked.join("\n")
    );
}

#[test]
fn the_parser_skips_code_and_reads_anchors_as_github_writes_them() {
    let text = "# The paper's text, its code, and ctxrace\n\
                See [a](a.md#x) and ![b](<pic one.png> \"title\").\n\
                `not [c](c.md)` and ``also `[d](d.md)` ``, then a `span\nover two lines [e](e.md)`.\n\
                \n\
                ```sh\n[f](f.md)\n```\n\
                [g](g_(1).md) [h](https://example.org) [i](mailto:x@example.org)\n\
                ## Repeat\n## Repeat\n";
    let found: Vec<(String, usize)> = links(text)
        .into_iter()
        .map(|l| (l.target, l.line))
        .collect();
    assert_eq!(
        found,
        [
            ("a.md#x".to_string(), 2),
            ("pic one.png".to_string(), 2),
            ("g_(1).md".to_string(), 9),
            ("https://example.org".to_string(), 9),
            ("mailto:x@example.org".to_string(), 9),
        ]
    );
    assert!(is_external("https://example.org") && is_external("mailto:x@example.org"));
    assert!(!is_external("docs/guides/race.md#the-rivals") && !is_external("a.md"));
    let heads = anchors(text);
    for a in ["the-papers-text-its-code-and-ctxrace", "repeat", "repeat-1"] {
        assert!(heads.contains(a), "{a} missing from {heads:?}");
    }
    assert_eq!(percent_decoded("pic%20one.png"), "pic one.png");
}
