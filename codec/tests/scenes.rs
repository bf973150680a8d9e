//! Compression on motion recorded from the shipped scenes — the numbers that matter, since the
//! bench (`mwb bench codec`) samples the same worlds — with the size split by what the bits
//! describe. The codec crate cannot run the simulator, so the tracks come from files: set
//! `MWB_SCENE_TRACKS` to a directory of `<scene>.tracks` files (layout below); it is a
//! measurement, ignored by default (without the variable it prints nothing). Run with
//! `MWB_SCENE_TRACKS=dir cargo test -p mwb-codec --release --test scenes -- --ignored --nocapture`;
//! `MWB_SCENE_MODEL=general` encodes as if the scenes had damping; `MWB_SCENE_PRESETS=standard`
//! (a comma-separated list of draft, standard, final) measures only those presets.
//!
//! ```text
//! f64 frame_dt, u8 model (0 general, 1 free flight), 3 × f64 gravity,
//! u32 worlds, per world: u32 segments, per segment: u32 bodies, per body: u32 frames,
//! frames × (3 × f64 position, 4 × f64 quaternion xyzw)     (all little endian)
//! ```
//!
//! The files are written by a few lines outside the workspace (the codec must not depend on the
//! sampler) around the bench's own sampling, per scene and world `i`:
//!
//! ```text
//! let seed = world_seed("bench-codec", &format!("scenes/{name}.toml"), i);
//! let scene = template.instantiate(seed);       // frame_dt = scene.settings.dt,
//!                                               // model = motion_model(&scene)
//! run_world_observed(&template, seed, RunOptions::default(),
//!                    &mut |_| ControlFlow::Continue(()), &mut |tracks| segments.push(tracks.to_vec()))
//! ```

use std::time::Instant;

use mwb_codec::{
    EncodeParams, MotionModel, Quality, SizeBreakdown, Track, WorldReader, encode_world,
};

struct SceneTracks {
    dt: f64,
    model: MotionModel,
    /// Every ~1 s segment of every world: one track per body.
    segments: Vec<Vec<Track>>,
}

fn read(bytes: &[u8]) -> Option<SceneTracks> {
    let mut at = 0usize;
    let mut take = |n: usize| {
        let s = bytes.get(at..at + n)?;
        at += n;
        Some(s)
    };
    let f64_ = |s: &[u8]| f64::from_le_bytes(s.try_into().unwrap_or([0; 8]));
    let u32_ = |s: &[u8]| u32::from_le_bytes(s.try_into().unwrap_or([0; 4])) as usize;
    let dt = f64_(take(8)?);
    let model_id = take(1)?[0];
    let g = [f64_(take(8)?), f64_(take(8)?), f64_(take(8)?)];
    let model = if model_id == 1 {
        MotionModel::FreeFlightGravity { g }
    } else {
        MotionModel::General
    };
    let mut segments = Vec::new();
    for _ in 0..u32_(take(4)?) {
        for _ in 0..u32_(take(4)?) {
            let mut seg = Vec::new();
            for _ in 0..u32_(take(4)?) {
                let mut t = Track::default();
                for _ in 0..u32_(take(4)?) {
                    let v: Vec<f64> = (0..7).map(|_| take(8).map(f64_)).collect::<Option<_>>()?;
                    t.positions.push([v[0], v[1], v[2]]);
                    t.rotations.push([v[3], v[4], v[5], v[6]]);
                }
                seg.push(t);
            }
            segments.push(seg);
        }
    }
    Some(SceneTracks {
        dt,
        model,
        segments,
    })
}

#[test]
#[ignore = "measurement: needs recorded tracks in MWB_SCENE_TRACKS; run with --ignored"]
fn shipped_scene_motion() {
    let Ok(dir) = std::env::var("MWB_SCENE_TRACKS") else {
        return;
    };
    for scene in ["tumble", "pachinko", "tower", "chute"] {
        let Ok(bytes) = std::fs::read(format!("{dir}/{scene}.tracks")) else {
            continue;
        };
        let mut s = read(&bytes).expect("well-formed tracks file");
        // `MWB_SCENE_MODEL=general`: as if the scene had damping (the full quadratic everywhere).
        if std::env::var("MWB_SCENE_MODEL").is_ok_and(|m| m == "general") {
            s.model = MotionModel::General;
        }
        for quality in [Quality::Draft, Quality::Standard, Quality::Final] {
            if std::env::var("MWB_SCENE_PRESETS").is_ok_and(|list| {
                !list
                    .split(',')
                    .any(|q| q.eq_ignore_ascii_case(&format!("{quality:?}")))
            }) {
                continue;
            }
            let p = EncodeParams::from_quality(quality, s.dt, s.model);
            let (mut bytes, mut frames, mut secs) = (0usize, 0u64, 0.0f64);
            let mut decode_secs = 0.0f64;
            let (mut pos_segs, mut rot_segs) = (0u64, 0u64);
            let (mut e, mut a) = (0.0f64, 0.0f64);
            let mut parts = SizeBreakdown::default();
            for seg in &s.segments {
                let t0 = Instant::now();
                let w = encode_world(seg, &p).expect("encodes");
                secs += t0.elapsed().as_secs_f64();
                bytes += w.bytes.len();
                frames += w.stats.object_frames;
                pos_segs += w.stats.position_segments;
                rot_segs += w.stats.rotation_segments;
                e = e.max(w.stats.max_position_error);
                a = a.max(w.stats.max_rotation_error);
                let b = &w.stats.breakdown;
                parts.header_and_index += b.header_and_index;
                parts.starts += b.starts;
                parts.position_segments += b.position_segments;
                parts.position_coefficients += b.position_coefficients;
                parts.rotation_segments += b.rotation_segments;
                parts.rotation_coefficients += b.rotation_coefficients;
                parts.keys += b.keys;
                parts.padding += b.padding;
                // The fastest of three decodes: a busy machine's preemptions are not the codec's.
                let mut fastest = f64::INFINITY;
                for _ in 0..3 {
                    let t0 = Instant::now();
                    let decoded = WorldReader::new(&w.bytes).and_then(|r| r.decode_all());
                    fastest = fastest.min(t0.elapsed().as_secs_f64());
                    assert_eq!(decoded.expect("decodes").len(), seg.len());
                }
                decode_secs += fastest;
            }
            let obj_s = frames as f64 * s.dt;
            println!(
                "{scene:<9} {quality:<8?} {:>7.1} B/(obj·s)  ×f32 {:>5.1}  segs/s pos {:>5.2} rot {:>5.2}  \
                 err {:.4} {:.4}  encode {:>4.0} decode {:>3.0} ns/obj-frame",
                bytes as f64 / obj_s,
                frames as f64 * 28.0 / bytes as f64,
                pos_segs as f64 / obj_s,
                rot_segs as f64 / obj_s,
                e / p.e_max,
                a / p.theta_max,
                secs * 1e9 / frames as f64,
                decode_secs * 1e9 / frames as f64,
            );
            let per = |bits: u64| bits as f64 / 8.0 / obj_s;
            println!(
                "    B/(obj·s): header+index {:.1}, starts {:.1}, pos types+lengths {:.1}, \
                 pos coefficients {:.1}, rot types+lengths {:.1}, rot coefficients {:.1}, \
                 keys {:.1}, padding {:.1}",
                per(parts.header_and_index),
                per(parts.starts),
                per(parts.position_segments),
                per(parts.position_coefficients),
                per(parts.rotation_segments),
                per(parts.rotation_coefficients),
                per(parts.keys),
                per(parts.padding),
            );
        }
    }
}
