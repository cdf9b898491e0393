//! The INI and HAL files of a headless LinuxCNC simulating geocal's machine: trivkins XYZ,
//! one linear joint per axis in mm, the machine's travel as soft limits, the velocity and
//! acceleration limits, and each joint's compensation table. The HAL file loops every
//! joint's `motor-pos-cmd` back to `motor-pos-fb` (a perfect servo: the simulated steel
//! follows the command, trim included).

use std::fmt::Write as _;
use std::path::PathBuf;

use crate::config::Config;

/// A joint's compensation table as LinuxCNC loads it (`[JOINT_n] COMP_FILE`).
#[derive(Debug, Clone, PartialEq)]
pub struct CompFile {
    /// Joint (= axis) index: x 0, y 1, z 2.
    pub joint: usize,
    pub file: PathBuf,
    /// `COMP_FILE_TYPE`: 0 (nominal, forward position, reverse position) or 1 (nominal,
    /// forward trim, reverse trim).
    pub comp_type: u8,
}

/// What the INI says about the machine, in SI units (written in mm).
#[derive(Debug, Clone, PartialEq)]
pub struct MachineSetup {
    /// Soft limits of x, y, z (metres, machine coordinates).
    pub travel_m: [[f64; 2]; 3],
    pub max_velocity_m_s: f64,
    pub max_acceleration_m_s2: f64,
    /// The motion controller's servo period (LinuxCNC's `SERVO_PERIOD`).
    pub servo_period_s: f64,
    pub comp_files: Vec<CompFile>,
}

impl Default for MachineSetup {
    fn default() -> Self {
        Self {
            travel_m: [[0.0, 1.0]; 3],
            max_velocity_m_s: 0.5,
            max_acceleration_m_s2: 1.0,
            servo_period_s: 1e-3,
            comp_files: Vec::new(),
        }
    }
}

impl MachineSetup {
    /// The LinuxCNC set-up of a real-controller HIL run, from the configuration.
    pub fn from_config(config: &Config) -> MachineSetup {
        let lc = config
            .hil
            .as_ref()
            .and_then(|h| h.linuxcnc.clone())
            .unwrap_or_default();
        let travel = |k: usize| {
            config
                .machine
                .travel_m
                .get(crate::compensate::AXES[k])
                .copied()
                .unwrap_or([-1.0, 1.0])
        };
        let axis_index = |a: &str| crate::compensate::AXES.iter().position(|x| *x == a);
        let mut comp_files: Vec<CompFile> = config
            .sim
            .iter()
            .flat_map(|s| &s.compensation)
            .filter_map(|c| {
                let comp_type = match c.format {
                    crate::compensate::TableFormat::LinuxcncType0 => 0,
                    crate::compensate::TableFormat::LinuxcncType1 => 1,
                    _ => return None,
                };
                Some(CompFile {
                    joint: c.axis_index()?,
                    file: c.file.clone(),
                    comp_type,
                })
            })
            .collect();
        comp_files.extend(lc.comp_files.iter().filter_map(|c| {
            Some(CompFile {
                joint: axis_index(&c.axis)?,
                file: c.file.clone(),
                comp_type: c.comp_type,
            })
        }));
        MachineSetup {
            travel_m: std::array::from_fn(travel),
            max_velocity_m_s: config.devices.machine.feed_m_s,
            max_acceleration_m_s2: lc.max_acceleration_m_s2,
            servo_period_s: lc.servo_period_s,
            comp_files,
        }
    }
}

const AXIS_LETTERS: [char; 3] = ['X', 'Y', 'Z'];

/// The HAL file's name in the INI's directory.
pub const HAL_FILE: &str = "geocal.hal";

/// `[EMCMOT] COMM_TIMEOUT`, seconds: how long LinuxCNC's task waits for the motion
/// controller to take a command. Without a realtime kernel a loaded computer stalls the servo
/// thread for seconds (1.8 s measured on 2 cores); past this wait the task drops the command
/// ("USRMOT: ERROR: command timeout" in its log) and an MDI move is lost or ends early
/// without an error (docs/linuxcnc.md). LinuxCNC's own configs say 1.0. Not more: at start-up
/// the task's first command can be lost to the motion module's initialisation, and the task
/// then waits this long before it publishes a status; linuxcncrsh gives up (and LinuxCNC
/// with it) when no status came within 10 s.
pub const COMM_TIMEOUT_S: f64 = 5.0;

/// `[DISPLAY] DISPLAY = linuxcncrsh`: the text interface on port 5007 is the only user
/// interface (no X display); it starts once the task is up.
pub fn ini_text(setup: &MachineSetup) -> String {
    let mm = |m: f64| m * 1e3;
    let vel = mm(setup.max_velocity_m_s);
    let acc = mm(setup.max_acceleration_m_s2);
    let servo_ns = (setup.servo_period_s * 1e9).round() as u64;
    let mut s = String::new();
    let _ = write!(
        s,
        "# Written by geocal for a real-controller HIL run.\n\
         [EMC]\nVERSION = 1.1\nMACHINE = geocal\n\n\
         [DISPLAY]\nDISPLAY = linuxcncrsh\n\n\
         [TASK]\nTASK = milltask\nCYCLE_TIME = 0.010\n\n\
         [RS274NGC]\nPARAMETER_FILE = geocal.var\n\n\
         [EMCMOT]\nEMCMOT = motmod\nCOMM_TIMEOUT = {COMM_TIMEOUT_S:.1}\nSERVO_PERIOD = {servo_ns}\n\n\
         [EMCIO]\nEMCIO = io\nCYCLE_TIME = 0.100\nTOOL_TABLE = geocal.tbl\n\n\
         [HAL]\nHALFILE = {HAL_FILE}\n\n\
         [TRAJ]\nCOORDINATES = XYZ\nLINEAR_UNITS = mm\nANGULAR_UNITS = degree\n\
         MAX_LINEAR_VELOCITY = {vel}\nMAX_LINEAR_ACCELERATION = {acc}\n\n\
         [KINS]\nKINEMATICS = trivkins coordinates=XYZ\nJOINTS = 3\n"
    );
    for (k, letter) in AXIS_LETTERS.iter().enumerate() {
        let [lo, hi] = setup.travel_m[k];
        let (lo, hi) = (mm(lo), mm(hi));
        let limits = format!(
            "MIN_LIMIT = {lo}\nMAX_LIMIT = {hi}\nMAX_VELOCITY = {vel}\nMAX_ACCELERATION = {acc}\n"
        );
        let _ = write!(
            s,
            "\n[AXIS_{letter}]\n{limits}\n[JOINT_{k}]\nTYPE = LINEAR\n{limits}"
        );
        // Homing where the joint stands (no switches): it is homed at 0, so 0 must lie in
        // the travel; HOME_SEQUENCE 0 homes all joints together.
        let _ = writeln!(s, "HOME = 0\nHOME_SEQUENCE = 0");
        for c in setup.comp_files.iter().filter(|c| c.joint == k) {
            let _ = writeln!(
                s,
                "COMP_FILE = {}\nCOMP_FILE_TYPE = {}",
                c.file.display(),
                c.comp_type
            );
        }
    }
    s
}

/// The minimal HAL: motion with its command handler and controller on the servo thread,
/// each joint's command looped to its feedback, the estop chain closed.
pub fn hal_text() -> String {
    let mut s = String::from(
        "# Written by geocal: a perfect servo per joint.\n\
         loadrt [KINS]KINEMATICS\n\
         loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS\n\
         addf motion-command-handler servo-thread\n\
         addf motion-controller servo-thread\n",
    );
    for k in 0..3 {
        let _ = writeln!(
            s,
            "net geocal-j{k} joint.{k}.motor-pos-cmd => joint.{k}.motor-pos-fb"
        );
    }
    s.push_str("net geocal-estop iocontrol.0.user-enable-out => iocontrol.0.emc-enable-in\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ini_names_travel_limits_and_comp_files_in_mm() {
        let setup = MachineSetup {
            travel_m: [[0.0, 1.4], [0.0, 2.4], [-0.5, 1.0]],
            comp_files: vec![CompFile {
                joint: 1,
                file: "/tmp/comp-y.txt".into(),
                comp_type: 1,
            }],
            ..MachineSetup::default()
        };
        let ini = ini_text(&setup);
        assert!(ini.contains("[JOINT_2]\nTYPE = LINEAR\nMIN_LIMIT = -500\nMAX_LIMIT = 1000\n"));
        assert!(ini.contains("MAX_ACCELERATION = 1000\n"));
        assert!(ini.contains("SERVO_PERIOD = 1000000\n"));
        assert!(ini.contains("COMM_TIMEOUT = 5.0\n"));
        assert!(
            ini.contains("HOME_SEQUENCE = 0\nCOMP_FILE = /tmp/comp-y.txt\nCOMP_FILE_TYPE = 1\n")
        );
        assert_eq!(ini.matches("COMP_FILE =").count(), 1);
        assert!(hal_text().contains("joint.2.motor-pos-cmd => joint.2.motor-pos-fb"));
    }
}
