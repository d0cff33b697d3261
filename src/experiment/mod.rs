//! The paper's experiment and beyond: random illumination scenarios ([`scenarios`]), a
//! resumable, shardable sweep of estimates over them ([`sweep`]), and charts of the results
//! ([`report`]).

pub mod report;
pub mod scenarios;
pub mod sweep;
