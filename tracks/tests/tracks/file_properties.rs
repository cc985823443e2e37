//! Property tests of the track file parsers on arbitrary input: CSV text, centreline and
//! raceline files, map yamls and the images they name are loaded or refused with a
//! [`TrackError`](ctxrace_tracks::TrackError) naming the file; never a panic.

use ctxrace_tracks::files::{load_centreline, load_raceline, parse_numeric_csv};
use ctxrace_tracks::OccupancyMap;
use proptest::prelude::*;
use std::path::Path;

/// CSV-like text: numbers, separators, comments, junk and non-finite values.
fn csv_text() -> impl Strategy<Value = String> {
    let cell = prop_oneof![
        4 => (-50.0f64..50.0).prop_map(|v| format!("{v}")),
        1 => Just("nan".to_string()),
        1 => Just("inf".to_string()),
        1 => Just("".to_string()),
        1 => "[a-z#;, ]{0,4}",
    ];
    let line = prop::collection::vec(cell, 0..9).prop_flat_map(|cells| {
        prop_oneof![Just(","), Just(";")].prop_map(move |sep| cells.join(sep))
    });
    prop::collection::vec(line, 0..40).prop_map(|lines| lines.join("\n"))
}

/// A map yaml that is sometimes well-formed, with an image that is sometimes a PNG.
fn map_yaml() -> impl Strategy<Value = String> {
    let number = prop_oneof![
        Just("0.05".to_string()),
        Just("-1".to_string()),
        Just("0".to_string()),
        Just(".nan".to_string()),
        Just("1e308".to_string()),
        "[a-z]{1,3}",
    ];
    (
        number.clone(),
        number.clone(),
        number,
        any::<bool>(),
        ".{0,40}",
    )
        .prop_map(|(resolution, x, yaw, known_keys, junk)| {
            if known_keys {
                format!(
                    "image: map.png\nresolution: {resolution}\norigin: [{x}, 0.0, {yaw}]\n\
                     negate: 0\noccupied_thresh: 0.45\nfree_thresh: 0.196\n"
                )
            } else {
                junk
            }
        })
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> std::path::PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn csv_text_parses_or_names_the_line(text in csv_text(), min_cols in 0usize..8) {
        match parse_numeric_csv(&text, min_cols, Path::new("t.csv")) {
            Ok(rows) => prop_assert!(rows.iter().all(|r| r.len() >= min_cols
                && r.iter().all(|v| v.is_finite()))),
            Err(e) => prop_assert!(e.to_string().contains("t.csv"), "{e}"),
        }
    }

    #[test]
    fn centrelines_and_racelines_load_or_fail(text in csv_text()) {
        let dir = tempfile::tempdir().unwrap();
        let path = write(dir.path(), "line.csv", text.as_bytes());
        if let Err(e) = load_centreline(&path) {
            prop_assert!(e.to_string().contains("line.csv"), "{e}");
        }
        if let Err(e) = load_raceline(&path) {
            prop_assert!(e.to_string().contains("line.csv"), "{e}");
        }
    }

    #[test]
    fn maps_load_or_fail(
        yaml in map_yaml(),
        image in prop_oneof![
            Just(None),
            prop::collection::vec(any::<u8>(), 0..300).prop_map(Some),
            (1u32..40, 1u32..40, any::<u8>()).prop_map(|(w, h, grey)| {
                let img = image::GrayImage::from_pixel(w, h, image::Luma([grey]));
                let mut png = Vec::new();
                img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                    .unwrap();
                Some(png)
            }),
        ],
    ) {
        let dir = tempfile::tempdir().unwrap();
        if let Some(bytes) = &image {
            write(dir.path(), "map.png", bytes);
        }
        let path = write(dir.path(), "map.yaml", yaml.as_bytes());
        if let Err(e) = OccupancyMap::load(&path) {
            let message = e.to_string();
            prop_assert!(message.contains("map.yaml") || message.contains("map.png"), "{message}");
        }
    }
}
