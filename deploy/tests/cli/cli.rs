//! The `ctxrace` command line, run as a separate process: the documented forms work, and bad input
//! gives a clear error (exit 1, no panic).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn ctxrace(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ctxrace"))
        .args(args)
        .env_remove("CTXRACE_TRACKS_DIR")
        .output()
        .expect("the binary runs")
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The reference material `../shared/<sub>`; a test that needs it fails without it.
fn shared(sub: &str) -> PathBuf {
    ctxrace_tracks::files::shared_reference(sub).unwrap_or_else(|e| panic!("{e}"))
}

/// Fails with a clear message: exit code 1 (2 for flag errors caught by clap), the message
/// contains `needle`, no panic.
fn fails_with(args: &[&str], needle: &str) {
    let o = ctxrace(args);
    let err = stderr(&o);
    assert!(matches!(o.status.code(), Some(1 | 2)), "{args:?}: {err}");
    assert!(
        err.contains(needle),
        "{args:?}: expected '{needle}' in: {err}"
    );
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
}

#[test]
fn race_on_a_generated_track_renders_traces_and_reports_json() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("race.png");
    let svg = dir.path().join("race.svg");
    let trace = dir.path().join("trace.csv");
    let o = ctxrace(&[
        "race",
        "generated:3",
        "--rivals",
        "2",
        "--context",
        "-0.3,0.2",
        "--ego",
        "pure-pursuit",
        "--seed",
        "5",
        "--render",
        png.to_str().unwrap(),
        "--trace",
        trace.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    assert_eq!(json["rivals"], 2);
    assert_eq!(json["context"][0], -0.3);
    let pg = json["progress"].as_f64().unwrap();
    assert!(pg > 0.0 && pg <= 1.0, "{json}");
    // a PNG with the right signature, and a trace with one row per decision plus the start
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    let rows: Vec<String> = std::fs::read_to_string(&trace)
        .unwrap()
        .lines()
        .map(String::from)
        .collect();
    assert_eq!(rows.len(), json["steps"].as_u64().unwrap() as usize + 2);
    let header: Vec<&str> = rows[0].split(',').collect();
    assert!(header.contains(&"rival2_speed") && header.contains(&"scan107"));
    assert_eq!(rows[1].split(',').count(), header.len());
    // the same seed gives the same episode, drawn as a picture or as an animation
    let gif = dir.path().join("race.gif");
    for render in [&svg, &gif] {
        let again = ctxrace(&[
            "race",
            "generated:3",
            "--rivals",
            "2",
            "--context",
            "-0.3,0.2",
            "--seed",
            "5",
            "--json",
            "--render",
            render.to_str().unwrap(),
        ]);
        assert_eq!(stdout(&again), stdout(&o));
    }
    assert!(std::fs::read_to_string(&svg).unwrap().contains("<svg"));
    assert_eq!(&std::fs::read(&gif).unwrap()[..6], b"GIF89a");
}

#[test]
fn vehicle_command_reproduces_the_reference_states() {
    let dir = shared("testdata/vehicle");
    let o = ctxrace(&[
        "vehicle",
        "--controls",
        dir.join("vehicle1_controls.csv").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let want = std::fs::read_to_string(dir.join("vehicle1_states.csv")).unwrap();
    let got = stdout(&o);
    assert_eq!(got.lines().count(), want.lines().count());
    for (g, w) in got.lines().zip(want.lines()).skip(1) {
        let g: Vec<f64> = g.split(',').map(|v| v.parse().unwrap()).collect();
        let w: Vec<f64> = w.split(',').map(|v| v.parse().unwrap()).collect();
        for (a, b) in g.iter().zip(&w) {
            assert!((a - b).abs() < 1e-6, "{g:?} vs {w:?}");
        }
    }
}

#[test]
fn track_info_and_raceline_export_on_the_paper_map() {
    let dir = shared("tracks");
    let d = dir.to_str().unwrap();
    let o = ctxrace(&["track", "info", "f1_esp", "--tracks-dir", d, "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let info: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    let length = info["length_m"].as_f64().unwrap();
    assert!((230.0..245.0).contains(&length), "{info}");
    assert!(info["raceline_lap_time_s"].as_f64().unwrap() > 20.0);
    let out = tempfile::tempdir().unwrap();
    let csv = out.path().join("esp_raceline.csv");
    let o = ctxrace(&[
        "track",
        "raceline",
        "f1_esp",
        "--tracks-dir",
        d,
        "--out",
        csv.to_str().unwrap(),
        "--v-max",
        "5",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = std::fs::read_to_string(&csv).unwrap();
    let speeds: Vec<f64> = text
        .lines()
        .map(|l| l.split(',').nth(5).unwrap().parse().unwrap())
        .collect();
    assert!(speeds.len() > 500);
    assert!(speeds.iter().all(|&v| v > 0.0 && v <= 5.0 + 1e-9));
    // the exported file loads back as a raceline of the same track
    let yaml = out.path().join("esp.yaml");
    std::fs::write(
        &yaml,
        "image: f1_esp.png\nresolution: 0.05\norigin: [-38.5, -24.4, 0]\n",
    )
    .unwrap();
    std::fs::copy(dir.join("f1_esp.png"), out.path().join("f1_esp.png")).unwrap();
    std::fs::copy(
        dir.join("f1_esp_centerline.csv"),
        out.path().join("esp_centerline.csv"),
    )
    .unwrap();
    let o = ctxrace(&[
        "track",
        "info",
        yaml.to_str().unwrap(),
        "--raceline-file",
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let back: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    assert!(
        (back["raceline_length_m"].as_f64().unwrap() - info["raceline_length_m"].as_f64().unwrap())
            .abs()
            < 0.5
    );
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn bad_input_gives_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // unknown track name lists what exists
    write(
        d,
        "oval.yaml",
        "image: oval.png\nresolution: 0.05\norigin: [0, 0, 0]\n",
    );
    write(
        d,
        "oval_centerline.csv",
        "0,0,1,1\n4,0,1,1\n4,4,1,1\n0,4,1,1\n",
    );
    fails_with(
        &[
            "track",
            "info",
            "nowhere",
            "--tracks-dir",
            d.to_str().unwrap(),
        ],
        "tracks found: oval",
    );
    // missing image named by the yaml
    fails_with(
        &["track", "info", "oval", "--tracks-dir", d.to_str().unwrap()],
        "oval.png",
    );
    // an image outside the yaml's folder is not opened
    write(
        d,
        "escape.yaml",
        "image: ../../../../etc/passwd\nresolution: 0.05\norigin: [0, 0, 0]\n",
    );
    write(
        d,
        "escape_centerline.csv",
        "0,0,1,1\n4,0,1,1\n4,4,1,1\n0,4,1,1\n",
    );
    fails_with(
        &["track", "info", d.join("escape.yaml").to_str().unwrap()],
        "image '../../../../etc/passwd' is not a file name beside the yaml",
    );
    // missing yaml file
    fails_with(
        &["track", "info", d.join("absent.yaml").to_str().unwrap()],
        "absent.yaml",
    );
    // a map and a centreline that do not match, too few points, a bad number
    {
        let shared = shared("tracks");
        // the map image lies beside the yaml, as it must
        std::fs::copy(shared.join("f1_esp.png"), d.join("f1_esp.png")).unwrap();
        let yaml = "image: f1_esp.png\nresolution: 0.05\norigin: [100, 100, 0]\n";
        write(d, "shifted.yaml", yaml);
        std::fs::copy(
            shared.join("f1_esp_centerline.csv"),
            d.join("shifted_centerline.csv"),
        )
        .unwrap();
        fails_with(
            &["track", "info", d.join("shifted.yaml").to_str().unwrap()],
            "outside the image",
        );
        let yaml = "image: f1_esp.png\nresolution: 0.05\norigin: [-38.5, -24.4, 0]\n";
        write(d, "few.yaml", yaml);
        write(d, "few_centerline.csv", "0,0,1,1\n1,0,1,1\n1,1,1,1\n");
        fails_with(
            &["track", "info", d.join("few.yaml").to_str().unwrap()],
            "3 distinct points",
        );
        write(d, "badnum.yaml", yaml);
        write(d, "badnum_centerline.csv", "0,0,1,1\n0.2,zero,1,1\n");
        fails_with(
            &["track", "info", d.join("badnum.yaml").to_str().unwrap()],
            "badnum_centerline.csv:2: column 2: 'zero' is not a number",
        );
    }
    // contexts out of range or malformed, bad generated seed, bad render extension
    fails_with(&["race", "generated:1", "--context", "2,0"], "out of range");
    fails_with(&["race", "generated:1", "--context", "0.1"], "two numbers");
    fails_with(&["race", "generated:x"], "must be a whole number");
    fails_with(
        &["race", "generated:1", "--rivals", "9"],
        "rivals = 9 must be 0 to 7",
    );
    fails_with(
        &[
            "train",
            "--inline",
            "--rivals",
            "9",
            "--run-dir",
            d.join("r9").to_str().unwrap(),
        ],
        "rivals = 9 must be 0 to 7",
    );
    fails_with(
        &[
            "race",
            "generated:1",
            "--render",
            d.join("x.jpg").to_str().unwrap(),
        ],
        ".png or .svg (a still) or .gif (an animation)",
    );
    // bad controls and configs
    let controls = write(d, "controls.csv", "steer,speed\n0.1,abc\n");
    fails_with(
        &["vehicle", "--controls", controls.to_str().unwrap()],
        "controls.csv:2: column 2: 'abc'",
    );
    let cfg = write(d, "cfg.toml", "rivalz = 2\n");
    fails_with(
        &["race", "generated:1", "--config", cfg.to_str().unwrap()],
        "unknown field `rivalz`",
    );
}

#[test]
fn export_onnx_writes_a_trained_agents_model_and_refuses_what_is_none() {
    let dir = tempfile::tempdir().unwrap();
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let checkpoint = repo.join("testdata/d6b5c40/cmask/checkpoint");
    let checkpoint = checkpoint.to_str().unwrap();
    let out = dir.path().join("cmask.onnx");
    let o = ctxrace(&["export", "onnx", checkpoint, out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let printed = stdout(&o);
    let size = std::fs::metadata(&out).unwrap().len();
    for line in [
        format!(
            "wrote {} ({size} bytes): cmask agent, ONNX opset 17",
            out.display()
        ),
        "inputs:  obs (B, 108), context (B, 2), is_first (B,), state (B, 34)".into(),
        "outputs: action (B, 2), state_out (B, 34), mask (B, 2)".into(),
        "state:   S = 34: h [0, 16), z [16, 32), prev_action [32, 34)".into(),
    ] {
        assert!(printed.contains(&line), "{line} in: {printed}");
    }
    // not a trained agent, an MLP policy file, a checkpoint name, a folder that is not there
    let other = dir.path().join("x.onnx");
    let other = other.to_str().unwrap();
    let configs = repo.join("configs");
    fails_with(
        &["export", "onnx", configs.to_str().unwrap(), other],
        "neither a checkpoint",
    );
    let mlp = write(dir.path(), "policy.safetensors", "not weights");
    fails_with(
        &["export", "onnx", mlp.to_str().unwrap(), other],
        "is an MLP policy file",
    );
    fails_with(
        &[
            "export",
            "onnx",
            checkpoint,
            other,
            "--checkpoint",
            "newest",
        ],
        "not best, latest",
    );
    fails_with(
        &["export", "onnx", checkpoint, "/no/such/folder/x.onnx"],
        "writing /no/such/folder/x.onnx",
    );
    fails_with(&["export", "tflite"], "unrecognized subcommand");
}

#[test]
fn train_refuses_a_run_it_cannot_make_before_writing_its_run_directory() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let tracks = d.join("tracks");
    std::fs::create_dir_all(&tracks).unwrap();
    let small = "[agent]\nalgo = \"sac\"\n[train]\nenv_steps = 600\nprefill = 100\n";
    for (k, (toml, actors, needles)) in [
        (
            "track = \"no_such_track\"\n",
            "1",
            &["loading track 'no_such_track'"][..],
        ),
        (
            "track = \"generated:abc\"\n",
            "1",
            &["generated:abc", "must be a whole number"][..],
        ),
        (
            "track = \"generated:0\"\n[race.lidar]\nbeams = 300\n",
            "1",
            &["lidar.beams = 300", "at most 256"][..],
        ),
        (
            // the code's warm-up runs only in the single-process trainer
            "track = \"generated:0\"\n[agent]\nalgo = \"sac\"\nwarmup = \"episodes\"\n\
             [train]\nenv_steps = 600\n",
            "1",
            &["warmup = \"episodes\"", "--inline"][..],
        ),
        (
            "track = \"generated:0\"\n[train]\nenv_steps = 500\nprefill = 500\n",
            "1",
            &["env_steps = 500", "prefill = 500", "no gradient step"][..],
        ),
        (
            "track = \"generated:0\"\n[agent.dreamer]\nlength = 32\n[replay]\ncapacity = 40\n\
             [train]\nenv_steps = 600\nprefill = 100\n",
            "2",
            &["[replay] capacity = 40", "ring of 20 steps"][..],
        ),
        (
            // rivals that are a trained agent need one, and one that can be read
            "track = \"generated:0\"\n[race.rival]\ndriver = \"policy\"\n",
            "1",
            &["driver = \"policy\" needs the trained agent", "policy = \"RUN_DIR\""][..],
        ),
        (
            "track = \"generated:0\"\n[race.rival]\ndriver = \"policy\"\npolicy = \"no/such/run\"\n",
            "1",
            &["[rival] policy = no/such/run", "neither a checkpoint"][..],
        ),
        (
            // rivals at three times the raceline's speed crash at the first bend on their own
            "track = \"generated:0\"\n[race.rival]\nspeed_factor = 3.0\nmax_speed = 20.0\n",
            "1",
            &[
                "not raceable in the training contexts",
                "hit a wall",
                "--no-track-check",
            ][..],
        ),
    ]
    .into_iter()
    .enumerate()
    {
        // a small run, so that only the probe's key is wrong
        let text = if toml.contains("[train]") {
            toml.to_string()
        } else {
            format!("{toml}{small}")
        };
        let cfg = write(d, &format!("probe{k}.toml"), &text);
        let run = d.join(format!("run{k}"));
        let started = std::time::Instant::now();
        let o = ctxrace(&[
            "train",
            cfg.to_str().unwrap(),
            "--actors",
            actors,
            "--tracks-dir",
            tracks.to_str().unwrap(),
            "--run-dir",
            run.to_str().unwrap(),
        ]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{text}: {err}");
        for needle in needles {
            assert!(err.contains(needle), "{text}: no '{needle}' in: {err}");
        }
        assert!(!run.exists(), "{text}: {} was created", run.display());
        let took = started.elapsed();
        assert!(
            took < std::time::Duration::from_secs(10),
            "{text}: {took:?}"
        );
    }
}

#[test]
fn the_shipped_scenarios_parse_and_match_their_presets() {
    let configs = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs");
    let read = |name: &str| {
        let text = std::fs::read_to_string(configs.join(name)).unwrap();
        ctxrace_config::RaceConfig::from_toml(&text).unwrap()
    };
    let defaults = ctxrace_config::RaceConfig {
        rivals: 3,
        ..Default::default()
    };
    assert_eq!(read("race.toml"), defaults);
    assert_eq!(
        read("scenarios/paper-code.toml"),
        ctxrace_config::RaceConfig::paper_code()
    );
}

#[test]
fn bench_sim_reports_throughput_as_json() {
    let o = ctxrace(&[
        "bench",
        "sim",
        "generated:2",
        "--rivals",
        "1",
        "--seconds",
        "0.3",
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    let decisions = r["decisions"].as_u64().unwrap();
    assert!(decisions > 100, "{r}");
    let per_s = r["decisions_per_s"].as_f64().unwrap();
    assert!((per_s - decisions as f64 / r["seconds"].as_f64().unwrap()).abs() < 1e-6 * per_s);
    assert!((r["physics_steps_per_s"].as_f64().unwrap() - per_s * 10.0).abs() < 1e-6 * per_s);
}

/// Writes a synthetic evaluation directory: a 7×7 context grid in ±0.3, training range ±0.15,
/// PG `pg - 0.3|c_v| - 0.2|c_θ|`, OT `ot`, A2A `a2a + 20|c_v|`.
fn synthetic_eval(dir: &Path, algo: &str, pg: f64, ot: f64, a2a: f64) {
    std::fs::create_dir_all(dir).unwrap();
    let meta = serde_json::json!({
        "algo": algo, "track": "generated:0", "rivals": 1, "train_seed": 0,
        "train_range": 0.15, "grid": 7, "range": 0.3, "laps": 50, "seed": 0, "source": algo,
    });
    write(dir, "meta.json", &meta.to_string());
    let mut csv = String::from(
        "context_speed,context_steer,in_distribution,laps,progress,overtakes,a2a,wall_crash,\
         lap_complete,episode_return\n",
    );
    for i in -3i32..=3 {
        for j in -3i32..=3 {
            let (cv, ct) = (i as f64 / 10.0, j as f64 / 10.0);
            let inside = i.abs() <= 1 && j.abs() <= 1;
            let p = pg - 0.3 * cv.abs() - 0.2 * ct.abs();
            let a = a2a + 20.0 * cv.abs();
            csv += &format!("{cv},{ct},{inside},50,{p},{ot},{a},0.1,0.2,3.5\n");
        }
    }
    write(dir, "contexts.csv", &csv);
}

#[test]
fn report_writes_tables_and_figures_with_best_marks() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // cMask as a training run (eval/ inside, training curves beside it), SAC as an eval dir
    synthetic_eval(&d.join("cmask-0/eval"), "cmask", 0.7, 0.1, 5.0);
    let mut training = String::from(
        "env_steps,grad_steps,actor,episode,context_speed,context_steer,progress,overtakes,a2a,\
         wall_crash,episode_return,steps\n",
    );
    for k in 0..40 {
        let progress = k as f64 / 50.0;
        training += &format!(
            "{},0,0,{k},0.1,-0.1,{progress},0,false,true,{},100\n",
            100 * (k + 1),
            10.0 * progress
        );
    }
    write(&d.join("cmask-0"), "episodes.csv", &training);
    synthetic_eval(&d.join("sac-0"), "sac", 0.4, 0.3, 15.0);
    write(&d.join("sac-0"), "episode.png", "not really a png");
    let out = d.join("out");
    let o = ctxrace(&[
        "report",
        d.join("cmask-0").to_str().unwrap(),
        d.join("sac-0").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert_eq!(stdout(&o), md);
    // cMask has the higher progress and fewer collisions, SAC more overtakes
    assert!(
        md.contains("| cMask | 1 | **0.6667 ± 0.0000** | 0.1000 ± 0.0000 | **6.3333 ± 0.0000** |"),
        "{md}"
    );
    assert!(
        md.contains("| SAC | 1 | 0.3667 ± 0.0000 | **0.3000 ± 0.0000** |"),
        "{md}"
    );
    for name in ["table1.csv", "table2.csv", "table3.csv"] {
        let text = std::fs::read_to_string(out.join(name)).unwrap();
        assert!(text.lines().count() > 1, "{name}: {text}");
    }
    let table2 = std::fs::read_to_string(out.join("table2.csv")).unwrap();
    assert!(table2.starts_with("track,rivals,algo,baseline,seeds,split,pg_mean,pg_std,pg_best"));
    for name in [
        "heatmap_cmask_generated_0_1r.png",
        "heatmap_sac_generated_0_1r.svg",
        "training_generated_0_1r.png",
        "rival_speed_generated_0.png",
        "rival_lines_generated_0.svg",
        "episode_sac_generated_0_1r_seed0.png",
    ] {
        assert!(out.join(name).is_file(), "{name} missing");
    }
    let png = std::fs::read(out.join("heatmap_cmask_generated_0_1r.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    assert!(md.contains("![heatmap_cmask_generated_0_1r.png](heatmap_cmask_generated_0_1r.png)"));
    // bad runs are named
    fails_with(
        &["report", d.join("nowhere").to_str().unwrap()],
        "nowhere: no such directory",
    );
    fails_with(
        &["report", out.to_str().unwrap()],
        "neither an evaluation directory",
    );
}

/// A tiny cMask experiment: a few gradient steps on the generated track.
const TINY_CMASK: &str = include_str!("../../../testdata/tiny-cmask.toml");

#[test]
fn inline_training_then_evaluation_report_and_race_with_the_policy() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write(dir.path(), "tiny.toml", TINY_CMASK);
    let run = dir.path().join("run");
    let run_s = run.to_str().unwrap();
    let o = ctxrace(&[
        "train",
        cfg.to_str().unwrap(),
        "--inline",
        "--run-dir",
        run_s,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("trained cmask for 300 env steps"),
        "{}",
        stdout(&o)
    );
    // the first look: the learning curve as a table and a picture, then the short evaluation
    let out = stdout(&o);
    let table = out.find("learning curve: ").expect(&out);
    let first_look = out.find("PG in").expect(&out);
    assert!(table < first_look, "{out}");
    assert!(
        out[table..first_look].contains("env steps      PG   return"),
        "{out}"
    );
    let curve = std::fs::read(run.join("learning_curve.png")).unwrap();
    assert!(
        curve.starts_with(b"\x89PNG"),
        "learning_curve.png is no PNG"
    );
    let episodes = std::fs::read_to_string(run.join("episodes.csv")).unwrap();
    assert!(episodes.starts_with("env_steps,grad_steps,actor,episode"));
    let checkpoints: Vec<_> = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .map(|c| c.unwrap().path())
        .collect();
    assert!(checkpoints.len() > 1, "{checkpoints:?}");
    for c in checkpoints {
        // the peak of the smoothed training return keeps the acting policy only
        let files: &[&str] = if c.ends_with("best") {
            &["policy.safetensors", "agent.toml", "best.toml"]
        } else {
            &[
                "policy.safetensors",
                "agent.toml",
                "state.toml",
                "returns.toml",
                "opt_model.safetensors",
            ]
        };
        for file in files {
            assert!(c.join(file).exists(), "{} has no {file}", c.display());
        }
    }
    // TensorBoard event files: the learner's losses and the training episodes
    let tags = ctxrace_learner::tensorboard::scalar_tags(&run).unwrap();
    for tag in [
        "episode/progress",
        "episode/return",
        "episode/a2a",
        "model/loss",
        "mask/q_loss",
    ] {
        assert!(tags.contains(tag), "no {tag} in {tags:?}");
    }
    // a second run into the same directory is refused
    fails_with(
        &[
            "train",
            cfg.to_str().unwrap(),
            "--inline",
            "--run-dir",
            run_s,
        ],
        "already holds a run",
    );

    let eval = |extra: &[&str]| {
        let mut args = vec![
            "eval",
            run_s,
            "--grid",
            "2",
            "--laps",
            "2",
            "--workers",
            "2",
        ];
        args.extend_from_slice(extra);
        ctxrace(&args)
    };
    let o = eval(&[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("cmask on generated:0 with 1 rival(s): 4 contexts x 2 laps"));
    let rows = |name: &str| {
        std::fs::read_to_string(run.join("eval").join(name))
            .unwrap()
            .lines()
            .count()
    };
    assert_eq!(rows("episodes.csv"), 1 + 4 * 2);
    assert_eq!(rows("contexts.csv"), 1 + 4);
    assert!(run.join("eval/episode.png").exists());
    // cMask's masks: one row per decision of every episode, in the mask's range
    let gz = std::fs::File::open(run.join("eval/masks.csv.gz")).unwrap();
    let mut masks = csv::Reader::from_reader(flate2::read::MultiGzDecoder::new(gz));
    assert_eq!(
        masks.headers().unwrap(),
        vec![
            "context_speed",
            "context_steer",
            "lap",
            "step",
            "progress",
            "x",
            "y",
            "mask_speed",
            "mask_steer"
        ]
    );
    let masks: Vec<Vec<f64>> = masks
        .records()
        .map(|r| r.unwrap().iter().map(|v| v.parse().unwrap()).collect())
        .collect();
    let mut episodes = csv::Reader::from_path(run.join("eval/episodes.csv")).unwrap();
    let steps_column = episodes
        .headers()
        .unwrap()
        .iter()
        .position(|h| h == "steps");
    let decisions: f64 = episodes
        .records()
        .map(|r| r.unwrap()[steps_column.unwrap()].parse::<f64>().unwrap())
        .sum();
    assert_eq!(masks.len() as f64, decisions);
    for m in &masks {
        assert!([m[0], m[1]].iter().all(|c| c.abs() <= 0.3 + 1e-9), "{m:?}");
        assert!(
            (0.0..=1.0).contains(&m[7]) && (0.0..=1.0).contains(&m[8]),
            "{m:?}"
        );
        assert!(m[4] > -0.1 && m[4] <= 1.5 && m[5].is_finite() && m[6].is_finite());
    }
    // the first decision of an episode is taken on the start line
    assert!(masks
        .iter()
        .filter(|m| m[3] == 0.0)
        .all(|m| m[4].abs() < 0.01));
    let parts = std::fs::read_dir(run.join("eval")).unwrap();
    assert!(!parts
        .map(|p| p.unwrap().file_name().into_string().unwrap())
        .any(|name| name.starts_with("masks.part-")));
    // the paper's protocol by default: the best checkpoint, sampled actions
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval/meta.json")).unwrap())
            .unwrap();
    assert_eq!(
        (meta["checkpoint"].as_str(), meta["act"].as_str()),
        (Some("best"), Some("sample"))
    );
    assert!(meta["source"].as_str().unwrap().ends_with("best"), "{meta}");
    let other = dir.path().join("eval-latest-mode");
    let o = eval(&[
        "--checkpoint",
        "latest",
        "--act",
        "mode",
        "--out",
        other.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let meta = std::fs::read_to_string(other.join("meta.json")).unwrap();
    assert!(meta.contains("\"checkpoint\": \"latest\"") && meta.contains("\"act\": \"mode\""));
    let o = eval(&["--checkpoint", "step-7"]);
    assert!(
        !o.status.success() && stderr(&o).contains("no step-7 checkpoint"),
        "{}",
        stderr(&o)
    );
    let o = eval(&["--checkpoint", "newest"]);
    assert!(
        !o.status.success() && stderr(&o).contains("not best, latest, step-N"),
        "{}",
        stderr(&o)
    );
    // resuming a finished evaluation runs nothing new; another grid needs --fresh
    let parts = std::fs::read_dir(run.join("eval")).unwrap().count();
    assert!(eval(&[]).status.success());
    assert_eq!(std::fs::read_dir(run.join("eval")).unwrap().count(), parts);
    let o = eval(&["--seed", "5"]);
    assert!(
        !o.status.success() && stderr(&o).contains("--fresh"),
        "{}",
        stderr(&o)
    );

    let out = dir.path().join("report");
    let o = ctxrace(&["report", run_s, "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read_to_string(out.join("report.md"))
        .unwrap()
        .contains("cMask"));
    let masks = std::fs::read_to_string(out.join("masks.csv")).unwrap();
    assert_eq!(masks.lines().count(), 1 + 4, "{masks}");
    for figure in ["mask_heatmap", "mask_along", "mask_track"] {
        let png = out.join(format!("{figure}_cmask_generated_0_1r.png"));
        assert!(
            std::fs::metadata(&png).unwrap().len() > 1000,
            "{}",
            png.display()
        );
    }

    let o = ctxrace(&["race", "generated:0", "--policy", run_s, "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("\"ego\": \"cmask\""), "{}", stdout(&o));
    let o = ctxrace(&["eval", dir.path().join("nothing").to_str().unwrap()]);
    assert!(
        !o.status.success() && stderr(&o).contains("neither a checkpoint"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn eval_races_only_the_chosen_contexts() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ev");
    let args = |contexts: &str| {
        ctxrace(&[
            "eval",
            "pure-pursuit",
            "--track",
            "generated:0",
            "--rivals",
            "1",
            "--grid",
            "3",
            "--laps",
            "1",
            "--workers",
            "1",
            "--contexts",
            contexts,
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let o = args("skip-first:7");
    assert!(o.status.success(), "{}", stderr(&o));
    let summary = std::fs::read_to_string(out.join("contexts.csv")).unwrap();
    // the last two of the 3 x 3 grid, both at c_v = 0.3
    assert_eq!(summary.lines().count(), 3, "{summary}");
    assert!(
        summary.lines().skip(1).all(|l| l.starts_with("0.3,")),
        "{summary}"
    );
    let meta = std::fs::read_to_string(out.join("meta.json")).unwrap();
    assert!(meta.contains("\"contexts\""), "{meta}");
    let o = args("9");
    assert!(
        !o.status.success() && stderr(&o).contains("--contexts \"9\": 9 is outside the grid"),
        "{}",
        stderr(&o)
    );
}

/// A matrix of two tiny SAC runs on a generated track, trained with `actors` actors (0:
/// inline) and evaluated on one context for one lap.
fn tiny_matrix(dir: &Path, actors: usize, env_steps: u64) -> PathBuf {
    write(
        dir,
        "base.toml",
        &format!(
            "track = \"generated:0\"\n[race]\nmax_time = 10.0\n[agent]\nalgo = \"sac\"\n\
             [agent.sac]\nhidden = 16\nbatch_size = 16\n[train]\nenv_steps = {env_steps}\n\
             prefill = 100\ntrain_ratio = 0.25\ncheckpoint_every = 20\nlog_every = 10\n"
        ),
    );
    write(
        dir,
        "matrix.toml",
        &format!(
            "base = \"base.toml\"\nalgos = [\"sac\"]\ntracks = [\"generated:0\"]\nrivals = [1]\n\
             seeds = [0, 1]\n[train]\nactors = {actors}\n[eval]\ngrid = 1\nlaps = 1\n"
        ),
    )
}

#[test]
fn a_sweep_runs_its_matrix_once_and_its_emitted_commands_do_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let matrix = tiny_matrix(dir.path(), 0, 300);
    let out = dir.path().join("sweep");
    let sweep = |extra: &[&str]| {
        let mut args = vec![
            "sweep",
            matrix.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        ctxrace(&args)
    };
    let o = sweep(&["--jobs", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("2 runs evaluated"), "{}", stdout(&o));
    for name in ["sac-generated_0-1r-s0", "sac-generated_0-1r-s1"] {
        assert!(out.join(name).join("eval/contexts.csv").is_file(), "{name}");
    }
    assert!(out.join("report/report.md").is_file());
    // a finished sweep runs nothing again
    let trained = std::fs::metadata(out.join("sac-generated_0-1r-s0/config.toml"))
        .unwrap()
        .modified()
        .unwrap();
    let o = sweep(&["--jobs", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let again = std::fs::metadata(out.join("sac-generated_0-1r-s0/config.toml"))
        .unwrap()
        .modified()
        .unwrap();
    assert_eq!(trained, again);

    // the emitted commands run one run each, exactly as the local sweep did
    let o = sweep(&["--jobs", "2", "--emit", "slurm"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let script = dir.path().join("sweep.sbatch");
    std::fs::write(&script, stdout(&o)).unwrap();
    let syntax = std::process::Command::new("bash")
        .arg("-n")
        .arg(&script)
        .output()
        .unwrap();
    assert!(syntax.status.success(), "{}", stderr(&syntax));
    assert!(stdout(&o).contains("#SBATCH --array=0-1"), "{}", stdout(&o));
    let o = sweep(&["--jobs", "2", "--emit", "list"]);
    let lines: Vec<String> = stdout(&o).lines().map(String::from).collect();
    assert_eq!(lines.len(), 2, "{lines:?}");
    let elsewhere = dir.path().join("elsewhere");
    let first = lines[0].replace(out.to_str().unwrap(), elsewhere.to_str().unwrap());
    let task = std::process::Command::new("bash")
        .args(["-c", &first])
        .output()
        .unwrap();
    assert!(task.status.success(), "{}", stderr(&task));
    for file in ["config.toml", "eval/contexts.csv", "eval/episodes.csv"] {
        let a = std::fs::read_to_string(out.join("sac-generated_0-1r-s0").join(file)).unwrap();
        let b =
            std::fs::read_to_string(elsewhere.join("sac-generated_0-1r-s0").join(file)).unwrap();
        assert_eq!(a, b, "{file} differs");
    }
    fails_with(
        &["sweep", matrix.to_str().unwrap(), "--only", "algo=cmask"],
        "no run that --only admits",
    );
}

#[test]
fn an_interrupted_sweep_resumes_its_runs_from_their_checkpoints() {
    let dir = tempfile::tempdir().unwrap();
    // a target far past the first checkpoint (step 20 of 1475): a fast machine trained the
    // 350 steps of a 1500-step run to its end before the interrupt came
    let matrix = tiny_matrix(dir.path(), 1, 6000);
    let out = dir.path().join("sweep");
    let args = [
        "sweep",
        matrix.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--only",
        "seed=0",
    ];
    let run = out.join("sac-generated_0-1r-s0");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_ctxrace"))
        .args(args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let wait = |what: &str, done: &dyn Fn() -> bool| {
        let start = std::time::Instant::now();
        while !done() {
            assert!(start.elapsed().as_secs() < 120, "no {what} in time");
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
    };
    // the sweep and its run are locked while it runs (checked once its learner has started)
    wait("learner", &|| run.join("logs/learner.log").exists());
    fails_with(&args, "in use by another process");
    // interrupt it as soon as the learner has checkpointed
    wait("checkpoint", &|| {
        ctxrace_learner::checkpoint::latest_checkpoint(&run).is_some()
    });
    // SAFETY: signalling our own child.
    unsafe {
        libc::kill(child.id() as libc::pid_t, libc::SIGINT);
    }
    let status = child.wait().unwrap();
    assert!(!status.success(), "the interrupted sweep reports it");
    assert!(!run.join("eval/contexts.csv").exists());
    let o = ctxrace(&args);
    assert!(o.status.success(), "{}\n{}", stderr(&o), logs_below(&out));
    assert!(run.join("eval/contexts.csv").is_file());
    let learner = std::fs::read_to_string(run.join("logs/learner.log")).unwrap();
    assert!(learner.contains("learner resumed from"), "{learner}");
}

/// The last lines of every log file below `dir`, each under its path: what a failed run said.
fn logs_below(dir: &std::path::Path) -> String {
    let mut out = String::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "log") {
                let text = std::fs::read_to_string(&path).unwrap_or_default();
                let lines: Vec<&str> = text.lines().collect();
                let tail = lines[lines.len().saturating_sub(20)..].join("\n");
                out.push_str(&format!("--- {}\n{tail}\n", path.display()));
            }
        }
    }
    out
}

/// Serves the files below `root` over HTTP on a loopback port (404 for the rest); returns the
/// base URL. The server thread lives as long as the test process.
fn serve(root: PathBuf) -> String {
    use std::io::{BufRead, BufReader, Write as _};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let mut reader = BufReader::new(stream.try_clone().unwrap());
            let mut line = String::new();
            reader.read_line(&mut line).ok();
            let path = line.split_whitespace().nth(1).unwrap_or("/").to_string();
            let mut header = String::new();
            while reader.read_line(&mut header).is_ok_and(|n| n > 2) {
                header.clear();
            }
            let file = root.join(path.trim_start_matches('/'));
            let mut out = stream;
            match std::fs::read(&file) {
                Ok(body) if !path.contains("..") => {
                    write!(
                        out,
                        "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                        body.len()
                    )
                    .ok();
                    out.write_all(&body).ok();
                }
                _ => {
                    write!(
                        out,
                        "HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                    )
                    .ok();
                }
            }
        }
    });
    url
}

#[test]
fn tracks_download_from_both_repository_layouts_and_then_resolve_by_name() {
    let shared = shared("tracks");
    let mirror = tempfile::tempdir().unwrap();
    // the paper's repository: maps/NAME.*; the F1TENTH racetracks: NAME/NAME_map.*
    let maps = mirror.path().join("maps");
    std::fs::create_dir_all(&maps).unwrap();
    for f in [
        "f1_gbr.yaml",
        "f1_gbr.png",
        "f1_gbr_centerline.csv",
        "f1_gbr_raceline.csv",
    ] {
        std::fs::copy(shared.join(f), maps.join(f)).unwrap();
    }
    let monza = mirror.path().join("Monza");
    std::fs::create_dir_all(&monza).unwrap();
    for f in ["Monza_map.yaml", "Monza_map.png", "Monza_centerline.csv"] {
        std::fs::copy(shared.join("extra").join(f), monza.join(f)).unwrap();
    }
    let url = serve(mirror.path().to_path_buf());
    let data = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_ctxrace"))
            .args(args)
            .env_remove("CTXRACE_TRACKS_DIR")
            .env("CTXRACE_DATA_DIR", data.path())
            .output()
            .unwrap()
    };
    let o = run(&["track", "download", "f1_gbr", "Monza", "--from", &url]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("f1_gbr: f1_gbr.png, f1_gbr.yaml"),
        "{}",
        stdout(&o)
    );
    assert!(data.path().join("tracks/Monza/Monza_map.png").is_file());
    // names now resolve in the per-user folder, whatever the tracks folder
    let empty = tempfile::tempdir().unwrap();
    let o = run(&[
        "track",
        "info",
        "Monza",
        "--tracks-dir",
        empty.path().to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("track            Monza"),
        "{}",
        stdout(&o)
    );
    // unknown names, bad names and no network are clear errors
    let o = run(&["track", "download", "Atlantis", "--from", &url]);
    assert!(
        !o.status.success() && stderr(&o).contains("Atlantis/Atlantis_map.yaml: no such file"),
        "{}",
        stderr(&o)
    );
    let o = run(&["track", "download", "../etc"]);
    assert!(
        !o.status.success() && stderr(&o).contains("letters, digits, _ and - only"),
        "{}",
        stderr(&o)
    );
    let o = run(&[
        "track",
        "download",
        "f1_esp",
        "--from",
        "http://127.0.0.1:1",
    ]);
    assert!(
        !o.status.success() && stderr(&o).contains("check the network connection"),
        "{}",
        stderr(&o)
    );
}
