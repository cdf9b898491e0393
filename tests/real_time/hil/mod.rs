//! Hardware-in-the-loop runs of every plan kind over the emulated devices, in real time.

mod hexapod;
mod probe_install;
mod rotary;
mod run;
