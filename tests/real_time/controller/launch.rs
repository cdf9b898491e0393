//! The LinuxCNC launcher against the real LinuxCNC (`linuxcnc-uspace`): start headless in a
//! private namespace, talk linuxcncrsh, read HAL pins at full precision, shut down, and
//! leave no process, shared memory or lock behind, also when the test never calls shutdown.
//! Skips without LinuxCNC (with the reason), fails instead when `CI` is set.

use crate::common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::time::Duration;

use geocal::sim::linuxcnc::{self, LinuxCnc, MachineSetup};

/// Send one linuxcncrsh command and read its one-line reply (verbose on: every set is acked).
fn ask(stream: &mut TcpStream, reader: &mut BufReader<TcpStream>, line: &str) -> String {
    stream
        .write_all(format!("{line}\r\n").as_bytes())
        .expect("write");
    loop {
        let mut reply = String::new();
        reader.read_line(&mut reply).expect("read");
        let reply = reply.trim_matches(['\r', '\n']).to_string();
        if !reply.is_empty() {
            return reply;
        }
    }
}

/// Ask `query` until its reply satisfies `done`, for at most five minutes (a loaded machine
/// runs LinuxCNC's servo thread late); returns the last reply.
fn poll(
    stream: &mut TcpStream,
    reader: &mut BufReader<TcpStream>,
    query: &str,
    done: impl Fn(&str) -> bool,
) -> String {
    let deadline = std::time::Instant::now() + Duration::from_secs(300);
    loop {
        let reply = ask(stream, reader, query);
        if done(&reply) || std::time::Instant::now() > deadline {
            return reply;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn session(lcnc: &LinuxCnc) -> (TcpStream, BufReader<TcpStream>) {
    let stream = lcnc.connect().expect("connect in the namespace");
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    let reader = BufReader::new(stream.try_clone().unwrap());
    (stream, reader)
}

fn nothing_left() {
    assert!(
        linuxcnc::linuxcnc_shared_memory().is_empty(),
        "{:?}",
        linuxcnc::linuxcnc_shared_memory()
    );
    assert!(!std::path::Path::new("/tmp/linuxcnc.lock").exists());
}

pub fn linuxcnc_starts_moves_reports_trim_pins_and_shuts_down_clean() {
    if !common::linuxcnc_available() {
        return;
    }
    let setup = MachineSetup {
        travel_m: [[0.0, 1.0], [0.0, 1.0], [0.0, 0.5]],
        ..MachineSetup::default()
    };
    let lcnc = LinuxCnc::start(&setup, Duration::from_secs(120)).expect("LinuxCNC starts");
    // Nothing listens on the machine's own loopback: the ports are in the namespace.
    assert!(TcpStream::connect(("127.0.0.1", linuxcnc::RSH_PORT)).is_err());
    let (mut s, mut r) = session(&lcnc);
    assert!(ask(&mut s, &mut r, "hello EMC geocal 1.0").starts_with("HELLO ACK"));
    for cmd in [
        "set enable EMCTOO",
        "set echo off",
        "set verbose on",
        "set estop off",
        "set machine on",
        "set mode manual",
        "set home -1",
    ] {
        let reply = ask(&mut s, &mut r, cmd);
        assert!(reply.contains("ACK") || reply == cmd, "{cmd}: {reply}");
    }
    let homed = poll(&mut s, &mut r, "get joint_homed", |h| {
        h.starts_with("JOINT_HOMED YES YES YES")
    });
    assert!(homed.starts_with("JOINT_HOMED YES YES YES"), "{homed}");
    // The move is polled rather than waited on with `set set_wait done`: under load that wait
    // once never answered, and polling is what the driver does.
    for cmd in ["set mode mdi", "set set_wait received"] {
        assert!(ask(&mut s, &mut r, cmd).contains("ACK"), "{cmd}");
    }
    let mode = poll(&mut s, &mut r, "get mode", |m| m == "MODE MDI");
    assert_eq!(mode, "MODE MDI", "{}", lcnc.log_tail(30));
    assert!(ask(
        &mut s,
        &mut r,
        "set mdi g53 g0 x987.6543219 y12.5 z0.0000013"
    )
    .contains("ACK"));
    let pos = poll(&mut s, &mut r, "get abs_act_pos", |p| {
        p.starts_with("ABS_ACT_POS 987.654322 12.500000 0.000001")
    });
    assert!(
        pos.starts_with("ABS_ACT_POS 987.654322 12.500000 0.000001"),
        "{pos}\n{}",
        lcnc.log_tail(30)
    );

    // The HAL pins at full precision (halcmd would print 987.6543).
    let mut hal = lcnc
        .hal_reader(vec![
            "joint.0.motor-pos-cmd".into(),
            "joint.2.motor-pos-cmd".into(),
            "joint.0.backlash-corr".into(),
            "joint.0.backlash-filt".into(),
        ])
        .expect("HAL reader");
    // The last servo cycles may still be running when linuxcncrsh shows the rounded target.
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    let mut v = hal.read().expect("HAL values");
    while (v[0] - 987.6543219).abs() >= 1e-9 && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
        v = hal.read().expect("HAL values");
    }
    assert!((v[0] - 987.6543219).abs() < 1e-9, "{v:?}");
    assert!((v[1] - 1.3e-6).abs() < 1e-9, "{v:?}");
    assert_eq!((v[2], v[3]), (0.0, 0.0), "no table, no trim");
    drop(hal);
    drop((s, r));
    lcnc.shutdown().expect("clean shutdown");
    nothing_left();
}

pub fn a_missing_comp_file_fails_fast_and_a_dropped_instance_leaves_nothing() {
    if !common::linuxcnc_available() {
        return;
    }
    // The launcher refuses a table that is not there, before starting anything.
    let setup = MachineSetup {
        comp_files: vec![linuxcnc::CompFile {
            joint: 0,
            file: "/nonexistent/comp-x.txt".into(),
            comp_type: 1,
        }],
        ..MachineSetup::default()
    };
    let e = LinuxCnc::start(&setup, Duration::from_secs(120))
        .err()
        .expect("refused");
    assert!(e.to_string().contains("comp-x.txt"), "{e}");

    // An instance dropped without shutdown, with a HAL reader still attached: the watchdog
    // kills the namespace and removes the shared memory.
    let lcnc = LinuxCnc::start(&MachineSetup::default(), Duration::from_secs(120))
        .expect("LinuxCNC starts");
    let mut hal = lcnc
        .hal_reader(vec!["joint.1.motor-pos-cmd".into()])
        .expect("HAL reader");
    assert_eq!(hal.read().expect("value"), vec![0.0]);
    drop(lcnc);
    drop(hal);
    nothing_left();
}
