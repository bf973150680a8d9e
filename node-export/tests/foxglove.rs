//! The Foxglove export read back with the `mcap` crate: schema names and encodings Foxglove
//! requires, channels, message counts and times, and the transforms against the decoded motion.

mod common;

use common::{compound, shapes, tumble};
use foxglove::Encode;
use foxglove::messages::{FrameTransforms, SceneUpdate};
use mwb_export::foxglove::{SCENE_FRAME, SCENE_TOPIC, TF_TOPIC, WORLD_FRAME, body_frame};
use prost::Message as _;

#[test]
fn scene_update_and_frame_transforms_play_the_decoded_world() {
    let w = tumble(0xfeed);
    let bytes = mwb_export::foxglove::write(&w.export(Some(4))).unwrap_or_else(|e| panic!("{e}"));
    let frames = w.motion.frame_count();

    let summary = mcap::Summary::read(&bytes)
        .unwrap_or_else(|e| panic!("{e}"))
        .unwrap_or_else(|| panic!("no summary section"));
    let stats = summary.stats.unwrap_or_else(|| panic!("no statistics"));
    assert_eq!(stats.message_count, 1 + frames as u64);
    let mut schemas: Vec<(String, String)> = summary
        .schemas
        .values()
        .map(|s| (s.name.clone(), s.encoding.clone()))
        .collect();
    schemas.sort();
    assert_eq!(
        schemas,
        vec![
            ("foxglove.FrameTransforms".to_owned(), "protobuf".to_owned()),
            ("foxglove.SceneUpdate".to_owned(), "protobuf".to_owned()),
        ]
    );
    // Foxglove's own descriptor sets, as its SDK publishes them.
    for s in summary.schemas.values() {
        let want = match s.name.as_str() {
            "foxglove.SceneUpdate" => SceneUpdate::get_schema(),
            _ => FrameTransforms::get_schema(),
        }
        .unwrap_or_else(|| panic!("no schema"));
        assert_eq!(&s.data[..], &want.data[..], "{}", s.name);
        // A FileDescriptorSet that defines the named message in package `foxglove`.
        let fds = prost_types::FileDescriptorSet::decode(&s.data[..])
            .unwrap_or_else(|e| panic!("{}: {e}", s.name));
        let (package, message) = s
            .name
            .split_once('.')
            .unwrap_or_else(|| panic!("{}", s.name));
        let fields: Vec<String> = fds
            .file
            .iter()
            .filter(|f| f.package() == package)
            .flat_map(|f| &f.message_type)
            .filter(|m| m.name() == message)
            .flat_map(|m| m.field.iter().map(|f| f.name().to_owned()))
            .collect();
        let want: &[&str] = match message {
            "SceneUpdate" => &["deletions", "entities"],
            _ => &["transforms"],
        };
        assert_eq!(fields, want, "{}", s.name);
    }

    let mut scene_updates = Vec::new();
    let mut tf = Vec::new();
    for m in mcap::MessageStream::new(&bytes).unwrap_or_else(|e| panic!("{e}")) {
        let m = m.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(m.channel.message_encoding, "protobuf");
        match m.channel.topic.as_str() {
            SCENE_TOPIC => scene_updates
                .push(SceneUpdate::decode(&m.data[..]).unwrap_or_else(|e| panic!("{e}"))),
            TF_TOPIC => tf.push((
                m.log_time,
                FrameTransforms::decode(&m.data[..]).unwrap_or_else(|e| panic!("{e}")),
            )),
            t => panic!("unexpected topic {t}"),
        }
    }
    assert_eq!(scene_updates.len(), 1);
    let entities = &scene_updates[0].entities;
    assert_eq!(entities.len(), w.scene.statics.len() + w.scene.bodies.len());
    for b in &w.scene.bodies {
        let e = entities
            .iter()
            .find(|e| e.frame_id == body_frame(&b.name))
            .unwrap_or_else(|| panic!("no entity for {}", b.name));
        assert!(e.frame_locked);
        assert_eq!(e.cubes.len(), 1, "tumble's bodies are boxes");
    }
    assert_eq!(tf.len(), frames);
    for (k, (t, msg)) in tf.iter().enumerate() {
        assert_eq!(*t, (k as f64 * w.motion.frame_dt * 1e9).round() as u64);
        let root = &msg.transforms[0];
        assert_eq!(
            (root.parent_frame_id.as_str(), root.child_frame_id.as_str()),
            (WORLD_FRAME, SCENE_FRAME)
        );
        assert_eq!(msg.transforms.len(), 1 + w.scene.bodies.len());
        for (i, b) in w.scene.bodies.iter().enumerate() {
            let x = &msg.transforms[1 + i];
            assert_eq!(x.parent_frame_id, SCENE_FRAME);
            assert_eq!(x.child_frame_id, body_frame(&b.name));
            let p = x.translation.unwrap_or_else(|| panic!("no translation"));
            assert_eq!([p.x, p.y, p.z], w.motion.tracks[i].positions[k]);
            let q = x.rotation.unwrap_or_else(|| panic!("no rotation"));
            let d = w.motion.tracks[i].rotations[k];
            let dot = q.x * d[0] + q.y * d[1] + q.z * d[2] + q.w * d[3];
            assert!(
                (dot.abs() - 1.0).abs() < 1e-12,
                "frame {k} body {i}: {q:?} vs {d:?}"
            );
        }
    }
}

#[test]
fn every_shape_becomes_a_primitive_or_triangles() {
    let w = shapes(11);
    let bytes = mwb_export::foxglove::write(&w.export(None)).unwrap_or_else(|e| panic!("{e}"));
    let update = mcap::MessageStream::new(&bytes)
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|m| m.unwrap_or_else(|e| panic!("{e}")))
        .find(|m| m.channel.topic == SCENE_TOPIC)
        .map(|m| SceneUpdate::decode(&m.data[..]).unwrap_or_else(|e| panic!("{e}")))
        .unwrap_or_else(|| panic!("no scene update"));
    let by_id = |id: &str| {
        update
            .entities
            .iter()
            .find(|e| e.id == id)
            .unwrap_or_else(|| panic!("no entity {id}"))
    };
    assert_eq!(by_id("body/crate").cubes.len(), 1);
    assert_eq!(by_id("body/ball").spheres.len(), 1);
    assert_eq!(by_id("body/can").cylinders.len(), 1);
    for id in ["body/pill", "body/gem", "static/ground", "static/wedge"] {
        let t = &by_id(id).triangles;
        assert_eq!(t.len(), 1, "{id}");
        assert!(
            !t[0].indices.is_empty() && t[0].indices.len() % 3 == 0,
            "{id}"
        );
        assert!(
            t[0].indices
                .iter()
                .all(|&i| (i as usize) < t[0].points.len())
        );
    }
    assert_eq!(by_id("static/ground").frame_id, SCENE_FRAME);
}

/// A compound body is one entity (it follows one transform) holding every part at its pose in
/// the body's frame, each in its material's colour; a compound static is placed in the scene.
#[test]
fn a_compound_is_one_entity_with_every_part() {
    let w = compound(5);
    let bytes = mwb_export::foxglove::write(&w.export(None)).unwrap_or_else(|e| panic!("{e}"));
    let update = mcap::MessageStream::new(&bytes)
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|m| m.unwrap_or_else(|e| panic!("{e}")))
        .find(|m| m.channel.topic == SCENE_TOPIC)
        .map(|m| SceneUpdate::decode(&m.data[..]).unwrap_or_else(|e| panic!("{e}")))
        .unwrap_or_else(|| panic!("no scene update"));
    assert_eq!(update.entities.len(), 3, "ground, shelf, letter");
    let find = |id: &str| {
        update
            .entities
            .iter()
            .find(|e| e.id == id)
            .unwrap_or_else(|| panic!("no entity {id}"))
    };
    let letter = find("body/letter_l");
    assert!(letter.frame_locked);
    assert_eq!((letter.cubes.len(), letter.cylinders.len()), (1, 1));
    let at = |pose: Option<&foxglove::messages::Pose>| {
        pose.and_then(|p| p.position.as_ref())
            .map(|p| [p.x, p.y, p.z])
            .unwrap_or_else(|| panic!("no position"))
    };
    assert_eq!(at(letter.cubes[0].pose.as_ref()), [0.0, 0.25, 0.0]);
    assert_eq!(at(letter.cylinders[0].pose.as_ref()), [0.15, 0.0, 0.0]);
    let colour = |c: Option<&foxglove::messages::Color>| c.map(|c| [c.r, c.g, c.b]);
    assert_ne!(
        colour(letter.cubes[0].color.as_ref()),
        colour(letter.cylinders[0].color.as_ref()),
        "wood and steel"
    );
    // The shelf's parts: the static's position plus each part's.
    let shelf = find("static/shelf");
    let xs: Vec<f64> = shelf.cubes.iter().map(|c| at(c.pose.as_ref())[0]).collect();
    assert_eq!(xs, vec![2.0, 1.55]);
}
