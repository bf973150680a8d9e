//! Compression on motion recorded from the shipped scenes — the numbers that matter, since the
//! bench (`mwb bench codec`) samples the same worlds — with the size split by what the bits
//! describe. The codec crate cannot run the simulator, so the tracks come from files: set
//! `MWB_SCENE_TRACKS` to a directory of `<scene>.tracks` files (layout below); it is a
//! measurement, ignored by default (without the variable it prints nothing). Run with
//! `MWB_SCENE_TRACKS=dir cargo test -p mwb-codec --release --test scenes -- --ignored --nocapture`;
//! `MWB_SCENE_MODEL=general` encodes as if the scenes had damping; `MWB_SCENE_PRESETS=standard`
//! (a comma-separated list of draft, standard, final) measures only those presets, and
//! `MWB_SCENE_BOUNDS=0.005,0.01` measures other bounds (e_max in m, θ_max the same in rad).
//! Each breakdown line ends with an FNV-1a digest of every stream written: an encoder change
//! meant to keep the bytes (a speed-up) is checked by comparing the digests before and after.
//! `MWB_SCENE_STREAMS_OUT=dir` also writes the streams that contain free flights, one file each
//! (`<scene>_<preset>_<segment>.mwbm`): seeds for the fuzz target's corpus.
//!
//! ```text
//! f64 frame_dt, u8 model (0 general, 1 free flight), 3 × f64 gravity,
//! u32 worlds, per world: u32 segments, per segment: u32 bodies, per body: u32 frames,
//! frames × (3 × f64 position, 4 × f64 quaternion xyzw)     (all little endian)
//! optional trailer, per world: u8 has dynamics, then u32 substeps, f64 angular damping,
//! u32 bodies, per body: u8 has inertia, 3 × f64 principal moments
//! ```
//!
//! `mwb bench codec --tracks-out <dir>` writes the files: the bench's own worlds (seeds
//! `world_seed("bench-codec", "scenes/<name>.toml", i)`, sampled as a sampler does), with the
//! rotation dynamics the sampler hands its encoder (`MWB_SCENE_DYNAMICS=off` ignores them).

use std::time::Instant;

use mwb_codec::{
    EncodeParams, MotionModel, Quality, RotationDynamics, SizeBreakdown, Track, WorldReader,
    encode_world_with_dynamics,
};

struct SceneTracks {
    dt: f64,
    model: MotionModel,
    /// Every ~1 s segment of every world: one track per body.
    segments: Vec<Vec<Track>>,
    /// The world of each segment.
    world_of: Vec<usize>,
    /// Per world, its rotation dynamics (the optional trailer; `MWB_SCENE_DYNAMICS=off` ignores it).
    dynamics: Vec<Option<RotationDynamics>>,
}

fn read(bytes: &[u8]) -> Option<SceneTracks> {
    let mut r = Cursor { bytes, at: 0 };
    let dt = r.f64()?;
    let model_id = r.take(1)?[0];
    let g = [r.f64()?, r.f64()?, r.f64()?];
    let model = if model_id == 1 {
        MotionModel::FreeFlightGravity { g }
    } else {
        MotionModel::General
    };
    let mut segments = Vec::new();
    let mut world_of = Vec::new();
    let worlds = r.u32()?;
    for w in 0..worlds {
        for _ in 0..r.u32()? {
            world_of.push(w);
            let mut seg = Vec::new();
            for _ in 0..r.u32()? {
                let mut t = Track::default();
                for _ in 0..r.u32()? {
                    let v: Vec<f64> = (0..7).map(|_| r.f64()).collect::<Option<_>>()?;
                    t.positions.push([v[0], v[1], v[2]]);
                    t.rotations.push([v[3], v[4], v[5], v[6]]);
                }
                seg.push(t);
            }
            segments.push(seg);
        }
    }
    // The optional trailer: per world, its rotation dynamics.
    let mut dynamics = vec![None; worlds];
    if r.at < bytes.len() {
        for d in &mut dynamics {
            if r.take(1)?[0] == 0 {
                continue;
            }
            let substeps = r.u32()? as u32;
            let angular_damping = r.f64()?;
            let mut inertia = Vec::new();
            for _ in 0..r.u32()? {
                let has = r.take(1)?[0] != 0;
                let i = [r.f64()?, r.f64()?, r.f64()?];
                inertia.push(has.then_some(i));
            }
            *d = Some(RotationDynamics {
                substeps,
                angular_damping,
                inertia,
            });
        }
    }
    Some(SceneTracks {
        dt,
        model,
        segments,
        world_of,
        dynamics,
    })
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let s = self.bytes.get(self.at..self.at + n)?;
        self.at += n;
        Some(s)
    }

    fn f64(&mut self) -> Option<f64> {
        Some(f64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }

    fn u32(&mut self) -> Option<usize> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?) as usize)
    }
}

/// The bounds to measure: the presets (`MWB_SCENE_PRESETS` picks some), or `MWB_SCENE_BOUNDS`, a
/// comma-separated list of e_max values in metres, each with θ_max the same number in radians (as
/// the bench's rate–distortion sweep).
fn settings(dt: f64, model: MotionModel) -> Vec<(String, EncodeParams)> {
    if let Ok(list) = std::env::var("MWB_SCENE_BOUNDS") {
        return list
            .split(',')
            .map(|e| {
                let e: f64 = e
                    .trim()
                    .parse()
                    .expect("MWB_SCENE_BOUNDS: numbers in metres");
                let mut p = EncodeParams::from_quality(Quality::Standard, dt, model);
                (p.e_max, p.theta_max) = (e, e);
                (format!("{e}"), p)
            })
            .collect();
    }
    [Quality::Draft, Quality::Standard, Quality::Final]
        .into_iter()
        .filter(|quality| {
            std::env::var("MWB_SCENE_PRESETS").map_or(true, |list| {
                list.split(',')
                    .any(|q| q.eq_ignore_ascii_case(&format!("{quality:?}")))
            })
        })
        .map(|quality| {
            (
                format!("{quality:?}"),
                EncodeParams::from_quality(quality, dt, model),
            )
        })
        .collect()
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
        for (label, p) in settings(s.dt, s.model) {
            let (mut bytes, mut frames, mut secs) = (0usize, 0u64, 0.0f64);
            let mut decode_secs = 0.0f64;
            let (mut pos_segs, mut rot_segs) = (0u64, 0u64);
            let (mut e, mut a) = (0.0f64, 0.0f64);
            let mut parts = SizeBreakdown::default();
            let off = std::env::var("MWB_SCENE_DYNAMICS").is_ok_and(|v| v == "off");
            let streams_out = std::env::var("MWB_SCENE_STREAMS_OUT").ok();
            let mut free = 0u64;
            // FNV-1a over every stream: "same bytes" checks of exact encoder changes.
            let mut digest = 0xcbf2_9ce4_8422_2325u64;
            for (n, (seg, &world)) in s.segments.iter().zip(&s.world_of).enumerate() {
                let d = s.dynamics[world].as_ref().filter(|_| !off);
                let t0 = Instant::now();
                let w = encode_world_with_dynamics(seg, &p, d).expect("encodes");
                free += w.stats.free_rotation_segments;
                secs += t0.elapsed().as_secs_f64();
                if let Some(out) = &streams_out
                    && w.stats.free_rotation_segments > 0
                {
                    let label: String = label
                        .chars()
                        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
                        .collect();
                    std::fs::write(format!("{out}/{scene}_{label}_{n}.mwbm"), &w.bytes)
                        .expect("writes the stream");
                }
                bytes += w.bytes.len();
                for &b in &w.bytes {
                    digest = (digest ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
                }
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
                "{scene:<9} {label:<8} {:>7.1} B/(obj·s)  ×f32 {:>5.1}  segs/s pos {:>5.2} rot {:>5.2} \
                 (free {:>4.2})  err {:.4} {:.4}  encode {:>4.0} decode {:>3.0} ns/obj-frame",
                bytes as f64 / obj_s,
                frames as f64 * 28.0 / bytes as f64,
                pos_segs as f64 / obj_s,
                rot_segs as f64 / obj_s,
                free as f64 / obj_s,
                e / p.e_max,
                a / p.theta_max,
                secs * 1e9 / frames as f64,
                decode_secs * 1e9 / frames as f64,
            );
            let per = |bits: u64| bits as f64 / 8.0 / obj_s;
            println!(
                "    B/(obj·s): header+index {:.1}, starts {:.1}, pos types+lengths {:.1}, \
                 pos coefficients {:.1}, rot types+lengths {:.1}, rot coefficients {:.1}, \
                 keys {:.1}, padding {:.1}; digest {digest:016x}",
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
