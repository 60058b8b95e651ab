//! The live view against a real WebSocket client on 127.0.0.1: the Foxglove handshake, the
//! advertised channels, a subscription to each, and what arrives: every topic's message with a
//! payload that decodes; and the bandwidth cap measured at the client.

use duv_core::config::board::LiveSettings;
use duv_core::{Frame, FrameImage, ImageRgb8, Se3, Timestamp};
use duv_live::{LiveItem, LiveServer, PoseRecord, Topic, MESSAGE_OVERHEAD_BYTES, TOPICS};
use foxglove::messages as fg;
use foxglove::Decode;
use futures_util::{SinkExt, StreamExt};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

type Ws = WebSocketStream<MaybeTlsStream<TcpStream>>;

/// The subprotocol the `foxglove` crate's server negotiates.
const SUBPROTOCOL: &str = "foxglove.sdk.v1";
const PATIENCE: Duration = Duration::from_secs(20);

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap()
}

fn settings(max_kb_per_s: u32) -> LiveSettings {
    LiveSettings { bind: "127.0.0.1:0".into(), max_kb_per_s, ..LiveSettings::default() }
}

/// Connects, reads `serverInfo` and the advertised channels (topic -> channel id, schema name).
async fn connect(port: u16) -> (Ws, HashMap<String, (u64, String)>) {
    let mut req = format!("ws://127.0.0.1:{port}").into_client_request().unwrap();
    req.headers_mut().insert("sec-websocket-protocol", SUBPROTOCOL.parse().unwrap());
    let (mut ws, resp) = tokio_tungstenite::connect_async(req).await.expect("connect");
    assert_eq!(resp.headers().get("sec-websocket-protocol").unwrap(), SUBPROTOCOL);
    let mut channels = HashMap::new();
    let mut server_info = false;
    while channels.len() < TOPICS.len() {
        let msg = tokio::time::timeout(PATIENCE, ws.next()).await.expect("advertise in time").unwrap().unwrap();
        let Message::Text(text) = msg else { continue };
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        match v["op"].as_str().unwrap() {
            "serverInfo" => server_info = true,
            "advertise" => {
                for c in v["channels"].as_array().unwrap() {
                    channels.insert(c["topic"].as_str().unwrap().to_string(), (c["id"].as_u64().unwrap(), c["schemaName"].as_str().unwrap().to_string()));
                }
            }
            _ => {}
        }
    }
    assert!(server_info, "serverInfo comes first");
    (ws, channels)
}

/// Subscribes to every channel: subscription id i+1 for TOPICS[i].
async fn subscribe_all(ws: &mut Ws, channels: &HashMap<String, (u64, String)>) {
    let subs: Vec<_> = TOPICS.iter().enumerate().map(|(i, t)| serde_json::json!({"id": i as u64 + 1, "channelId": channels[*t].0})).collect();
    ws.send(Message::Text(serde_json::json!({"op": "subscribe", "subscriptions": subs}).to_string().into())).await.unwrap();
}

/// Waits until the server has every subscription.
fn wait_subscribed(server: &LiveServer) {
    let t0 = Instant::now();
    while !Topic::ALL.iter().all(|&t| server.watched(t)) {
        assert!(t0.elapsed() < PATIENCE, "subscriptions not seen by the server");
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// One `messageData` message: (topic, payload).
fn message_data(msg: &Message) -> Option<(&'static str, Vec<u8>)> {
    let Message::Binary(b) = msg else { return None };
    assert_eq!(b[0], 1, "opcode messageData");
    let sub = u32::from_le_bytes(b[1..5].try_into().unwrap()) as usize;
    Some((TOPICS[sub - 1], b[13..].to_vec()))
}

fn pose(seq: u64) -> PoseRecord {
    PoseRecord {
        t_ns: Timestamp::from_ns(1_000_000_000 + seq as i64 * 100_000_000),
        seq,
        world_from_cam: Se3::from_parts(nalgebra::Translation3::new(seq as f64 * 0.1, -0.5, 2.0), nalgebra::UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3)),
        state: "tracking",
        tracked: true,
        keyframe: Some(3),
        new_keyframe: None,
        loop_closed: false,
        segment: 0,
        why: None,
        value: None,
        limit: None,
    }
}

fn frame(seq: u64, w: usize, h: usize) -> Arc<Frame> {
    let mut img = ImageRgb8::new(w, h);
    for y in 0..h {
        for x in 0..w {
            img.set_pixel(x, y, [(x * 255 / w) as u8, (y * 255 / h) as u8, if (x / 8 + y / 8) % 2 == 0 { 60 } else { 190 }]);
        }
    }
    Arc::new(Frame { t_ns: Timestamp::from_ns(seq as i64 * 100_000_000), seq, image: FrameImage::Rgb8(img) })
}

/// `n` centres, coloured (R = index mod 256, G 7, B 9) or, without `colours`, by height.
fn cloud(n: usize, colours: bool) -> LiveItem {
    let centres = (0..n).map(|i| [i as f32 * 0.01, (i % 7) as f32, -((i % 13) as f32) * 0.1]).collect();
    let colours = if colours { (0..n).map(|i| [(i % 256) as u8, 7, 9]).collect() } else { Vec::new() };
    LiveItem::Cloud { t_ns: Timestamp::from_ns(5), centres_in_world: centres, colours }
}

#[test]
fn a_client_subscribes_and_receives_every_topic_decodable() {
    let rt = runtime();
    let mut server = LiveServer::start(&settings(100_000)).unwrap();
    let port = server.local_addr().port();
    assert_ne!(port, 0);
    let (mut ws, channels) = rt.block_on(connect(port));
    let schemas: Vec<_> = TOPICS.iter().map(|t| channels[*t].1.as_str()).collect();
    assert_eq!(schemas, ["foxglove.PoseInFrame", "foxglove.FrameTransform", "duv.TrackingState", "foxglove.CompressedImage", "foxglove.PosesInFrame", "foxglove.PointCloud"]);
    rt.block_on(subscribe_all(&mut ws, &channels));
    wait_subscribed(&server);
    assert_eq!(server.clients(), 1);

    let p = pose(7);
    server.publish(&LiveItem::Pose(p));
    server.publish(&LiveItem::Frame(frame(7, 160, 120)));
    server.publish(&LiveItem::Keyframe { id: 0, t_ns: Timestamp::from_ns(1), world_from_cam: Se3::identity() });
    server.publish(&LiveItem::Keyframe { id: 1, t_ns: Timestamp::from_ns(2), world_from_cam: p.world_from_cam });
    server.publish(&cloud(500, true));

    let mut got: HashMap<&str, Vec<Vec<u8>>> = HashMap::new();
    rt.block_on(async {
        // Pose, transform, state, image, two keyframe lists, a cloud.
        while got.values().map(Vec::len).sum::<usize>() < 7 {
            let msg = tokio::time::timeout(PATIENCE, ws.next()).await.expect("messages in time").unwrap().unwrap();
            if let Some((topic, payload)) = message_data(&msg) {
                got.entry(topic).or_default().push(payload);
            }
        }
    });
    let near = |a: &fg::Pose, b: &Se3| {
        let t = a.position.as_ref().unwrap();
        (t.x - b.translation.vector.x).abs() < 1e-12 && (t.z - b.translation.vector.z).abs() < 1e-12 && (a.orientation.as_ref().unwrap().w - b.rotation.quaternion().w).abs() < 1e-12
    };
    let pose_msg = fg::PoseInFrame::decode(&got["/slam/pose"][0][..]).unwrap();
    assert_eq!(pose_msg.frame_id, "world");
    assert!(near(pose_msg.pose.as_ref().unwrap(), &p.world_from_cam));
    assert_eq!(pose_msg.timestamp.unwrap().sec(), 1);
    let tf = fg::FrameTransform::decode(&got["/tf"][0][..]).unwrap();
    assert_eq!((tf.parent_frame_id.as_str(), tf.child_frame_id.as_str()), ("world", "camera"));
    assert!((tf.translation.unwrap().x - 0.7).abs() < 1e-12);
    let state: serde_json::Value = serde_json::from_slice(&got["/slam/state"][0]).unwrap();
    assert_eq!((state["seq"].as_u64(), state["state"].as_str(), state["keyframe"].as_u64(), state["tracked"].as_bool()), (Some(7), Some("tracking"), Some(3), Some(true)));
    // The camera: 160x120 at the default scale 0.5, a JPEG that decodes to 80x60.
    let img = fg::CompressedImage::decode(&got["/camera/image"][0][..]).unwrap();
    assert_eq!(img.format, "jpeg");
    let mut dec = zune_jpeg::JpegDecoder::new(&img.data[..]);
    let pixels = dec.decode().unwrap();
    assert_eq!(dec.dimensions(), Some((80, 60)));
    assert_eq!(pixels.len(), 80 * 60 * 3);
    // The keyframe lists: one pose, then two.
    let lists: Vec<_> = got["/slam/keyframes"].iter().map(|b| fg::PosesInFrame::decode(&b[..]).unwrap()).collect();
    assert_eq!(lists.iter().map(|l| l.poses.len()).collect::<Vec<_>>(), vec![1, 2]);
    assert!(near(&lists[1].poses[1], &p.world_from_cam));
    // The cloud: 500 points of 16 bytes, x y z as f32 first.
    let pc = fg::PointCloud::decode(&got["/map/gaussians"][0][..]).unwrap();
    assert_eq!((pc.point_stride, pc.data.len(), pc.fields.len()), (16, 500 * 16, 7));
    let x1 = f32::from_le_bytes(pc.data[16..20].try_into().unwrap());
    let y1 = f32::from_le_bytes(pc.data[20..24].try_into().unwrap());
    assert_eq!((x1, y1), (0.01, 1.0));
    assert_eq!(&pc.data[28..32], &[1, 7, 9, 255], "point 1's colour, opaque");
    let names: Vec<_> = pc.fields.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["x", "y", "z", "red", "green", "blue", "alpha"]);

    let stats = server.stats();
    assert_eq!((stats.sent.pose, stats.sent.camera, stats.sent.keyframes, stats.sent.cloud), (1, 1, 2, 1));
    assert_eq!((stats.messages_sent, stats.dropped_budget.total(), stats.unwatched, stats.clients_max), (7, 0, 0, 1));
    let stopped = Instant::now();
    server.stop();
    assert!(stopped.elapsed() < Duration::from_secs(2), "stop waited {:?}", stopped.elapsed());
}

/// 16 KiB/s against an offer of about 75 KiB/s for 3 s (poses at 30 Hz, 160x120 camera frames
/// at 30 Hz, a cloud every 0.5 s): the bytes the client receives stay within the cap over the
/// window plus the bucket and one message; every pose arrives; the camera is dropped first and
/// every drop is counted.
#[test]
fn the_bandwidth_cap_holds_at_the_client_and_drops_are_counted() {
    let rt = runtime();
    let kib_per_s = 16u32;
    let mut server = LiveServer::start(&settings(kib_per_s)).unwrap();
    let (mut ws, channels) = rt.block_on(connect(server.local_addr().port()));
    rt.block_on(subscribe_all(&mut ws, &channels));
    wait_subscribed(&server);

    // The client reads as the messages come, on its own thread (with its runtime, which owns
    // the connection), until 1.5 s of silence.
    let reader = std::thread::spawn(move || {
        let mut received: HashMap<&str, (u64, usize)> = HashMap::new();
        let (mut bytes, mut largest) = (0usize, 0usize);
        rt.block_on(async {
            while let Ok(Some(Ok(msg))) = tokio::time::timeout(Duration::from_millis(1500), ws.next()).await {
                if let Some((topic, payload)) = message_data(&msg) {
                    let r = received.entry(topic).or_default();
                    r.0 += 1;
                    r.1 += payload.len();
                    bytes += payload.len() + MESSAGE_OVERHEAD_BYTES;
                    largest = largest.max(payload.len() + MESSAGE_OVERHEAD_BYTES);
                }
            }
        });
        (received, bytes, largest)
    });
    let window = Duration::from_secs(3);
    let t0 = Instant::now();
    let mut offered = [0u64; 3]; // pose, camera, cloud
    let mut i = 0u64;
    while t0.elapsed() < window {
        server.publish(&LiveItem::Pose(pose(i)));
        server.publish(&LiveItem::Frame(frame(i, 160, 120)));
        offered[0] += 1;
        offered[1] += 1;
        if i.is_multiple_of(15) {
            server.publish(&cloud(2000, false));
            offered[2] += 1;
        }
        i += 1;
        std::thread::sleep(Duration::from_millis(33));
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let stats = server.stats();
    let (received, bytes, largest) = reader.join().unwrap();
    let rate = kib_per_s as f64 * 1024.0;
    let cap = rate * (elapsed + duv_live::budget::BURST_S) + largest as f64;
    println!("{bytes} bytes in {elapsed:.2} s (cap {cap:.0}); {stats:?}; received {received:?}");
    assert!(bytes as f64 <= cap, "{bytes} bytes received, cap {cap:.0}");
    assert_eq!(bytes as u64, stats.bytes_sent, "the client gets what the server counts");
    // Poses alone (about 9 kB/s) fit: none dropped, all received.
    assert_eq!((stats.sent.pose, stats.dropped_budget.pose), (offered[0], 0));
    assert_eq!(received["/slam/pose"].0, offered[0]);
    assert_eq!(received["/slam/state"].0, offered[0]);
    // Everything offered is sent or counted as dropped.
    assert_eq!(stats.sent.camera + stats.dropped_budget.camera, offered[1]);
    assert_eq!(stats.sent.cloud + stats.dropped_budget.cloud, offered[2]);
    assert!(stats.dropped_budget.camera > offered[1] / 2, "the camera is dropped first: {stats:?}");
    assert!(stats.sent.camera > 0, "some camera frames still go: {stats:?}");
    let frac = |sent: u64, offered: u64| sent as f64 / offered as f64;
    assert!(stats.sent.cloud >= 1 && frac(stats.sent.cloud, offered[2]) > frac(stats.sent.camera, offered[1]), "clouds go before the camera: {stats:?}");
    server.stop();
}
