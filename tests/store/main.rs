//! The contract of the job store and the artifact store
//! (`radiance::store`): what every pair of stores does alike, written once
//! as async checks over how a pair is opened (`contract`), and run here on
//! the embedded pair (`embedded`). Another backend runs the same checks
//! with `contract_tests!(its_opener)`.

#[macro_use]
mod contract;
mod embedded;
