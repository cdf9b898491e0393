//! Hardware-in-the-loop runs of every plan kind over the emulated devices, in real time. Their
//! fault injections use short time-outs (they must detect an injected silence), so they run in
//! a binary of their own, not beside LinuxCNC's scenarios in `real_time`.

#[path = "../common/mod.rs"]
mod common;

mod hexapod;
mod probe_install;
mod rotary;
mod run;
