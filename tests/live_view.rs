//! `duv run --live-view` end to end: a WebSocket client on 127.0.0.1 connects to the running
//! binary, subscribes to the pose and the state, and receives them for the run's frames; the
//! run ends on its own with the client still connected and prints what the live view sent.
//! Without the `live-view` feature the flag is refused with a message that says so.

use std::path::Path;
use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR")).env("RUST_LOG", "warn");
    c
}

fn run_args(out: &Path, addr: &str) -> Vec<String> {
    let mut v: Vec<String> = ["run", "--source", "sim:coastal,frames=60", "--width", "160", "--height", "120", "--no-map", "--no-progress", "--speed", "2", "--live-view", addr].map(String::from).to_vec();
    v.push("--out".into());
    v.push(out.display().to_string());
    v
}

#[cfg(not(feature = "live-view"))]
#[test]
fn without_the_feature_the_flag_is_refused_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let out = duv().args(run_args(&dir.path().join("run"), "127.0.0.1:0")).output().unwrap();
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(text.contains("--live-view") && text.contains("lacks the `live-view` feature"), "{text}");
    assert!(!dir.path().join("run").exists(), "nothing is written");
}

#[cfg(feature = "live-view")]
#[test]
fn a_client_receives_pose_and_state_of_the_run_and_the_run_ends_without_it() {
    use std::collections::{BTreeMap, BTreeSet};
    use std::io::Read;
    use std::net::{TcpListener, TcpStream};
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    use tungstenite::client::IntoClientRequest;
    use tungstenite::Message;

    // A free port, given to the run.
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let mut child = duv().args(run_args(&dir.path().join("run"), &addr)).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();

    // Connect as soon as the server listens.
    let stream = loop {
        match TcpStream::connect(&addr) {
            Ok(s) => break s,
            Err(_) if started.elapsed() < Duration::from_secs(60) => std::thread::sleep(Duration::from_millis(10)),
            Err(e) => panic!("the live view never listened on {addr}: {e}"),
        }
    };
    stream.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let mut req = format!("ws://{addr}").into_client_request().unwrap();
    req.headers_mut().insert("sec-websocket-protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut ws, _) = tungstenite::client(req, stream).expect("handshake");
    let mut channels: BTreeMap<String, u64> = BTreeMap::new();
    while !(channels.contains_key("/slam/pose") && channels.contains_key("/slam/state")) {
        if let Message::Text(t) = ws.read().unwrap() {
            let v: serde_json::Value = serde_json::from_str(&t).unwrap();
            if v["op"] == "advertise" {
                for c in v["channels"].as_array().unwrap() {
                    channels.insert(c["topic"].as_str().unwrap().into(), c["id"].as_u64().unwrap());
                }
            }
        }
    }
    let subscribe = serde_json::json!({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channels["/slam/pose"]}, {"id": 2, "channelId": channels["/slam/state"]}]});
    ws.send(Message::Text(subscribe.to_string().into())).unwrap();

    // Read until the server goes away (the run ended); the client never leaves first.
    let (mut poses, mut states) = (0usize, BTreeSet::new());
    let mut state_names = BTreeSet::new();
    loop {
        match ws.read() {
            Ok(Message::Binary(b)) => {
                assert_eq!(b[0], 1, "messageData");
                let payload = &b[13..];
                match u32::from_le_bytes(b[1..5].try_into().unwrap()) {
                    1 => {
                        use foxglove::Decode;
                        let p = foxglove::messages::PoseInFrame::decode(payload).expect("a PoseInFrame");
                        assert_eq!(p.frame_id, "world");
                        assert!(p.pose.unwrap().position.unwrap().x.is_finite());
                        poses += 1;
                    }
                    2 => {
                        let s: serde_json::Value = serde_json::from_slice(payload).expect("state JSON");
                        let seq = s["seq"].as_u64().unwrap();
                        assert!(seq < 60, "frame {seq} is not one of the run's 60");
                        assert!(states.insert(seq), "frame {seq} twice");
                        state_names.insert(s["state"].as_str().unwrap().to_string());
                    }
                    other => panic!("subscription {other} was never asked for"),
                }
            }
            Ok(_) => {}
            Err(_) => break,
        }
    }
    let status = child.wait().unwrap();
    let mut stdout = String::new();
    child.stdout.take().unwrap().read_to_string(&mut stdout).unwrap();
    let mut stderr = String::new();
    child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
    assert!(status.success(), "{stdout}\n{stderr}");
    assert!(started.elapsed() < Duration::from_secs(120), "the run took {:?}", started.elapsed());
    // The run is 3 s of frames; the client was there for most of them.
    assert!(states.len() >= 10 && poses == states.len(), "{poses} poses, {} states", states.len());
    assert!(state_names.iter().any(|s| s == "tracking"), "{state_names:?}");
    assert!(stderr.contains(&format!("live view on ws://{addr}")), "{stderr}");
    let line = stdout.lines().find(|l| l.starts_with(&format!("live view ws://{addr}:"))).unwrap_or_else(|| panic!("no live view line:\n{stdout}"));
    assert!(line.contains("at most 1 client(s)") && line.contains(", 0 poses (bandwidth)"), "{line}");
    let sent: usize = line.split(": ").nth(2).and_then(|s| s.split(' ').next()).and_then(|n| n.parse().ok()).unwrap_or_else(|| panic!("{line}"));
    assert!(sent >= poses, "{line}: {poses} received");
}

/// A port already taken: the run stops at once with the address in the message, before it
/// logs anything (so the folder is not left as a dive to resume).
#[cfg(feature = "live-view")]
#[test]
fn a_taken_port_is_an_error_before_anything_is_logged() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let dir = tempfile::tempdir().unwrap();
    let out = duv().args(run_args(&dir.path().join("run"), &addr)).output().unwrap();
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(text.contains(&format!("live view: cannot serve on {addr}")), "{text}");
    let segments = std::fs::read_dir(dir.path().join("run/log")).map(|d| d.count()).unwrap_or(0);
    assert_eq!(segments, 0, "nothing logged");
}
