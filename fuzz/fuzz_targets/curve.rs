//! The curve readers every transport uses (`Curve::from_json`, `Curve::from_obj`): the same
//! bytes through both, and a curve that reads must survive a JSON round trip.
#![no_main]
willow_fuzz::capped_allocator!();

use libfuzzer_sys::fuzz_target;
use willow::curve::Curve;

fuzz_target!(|data: &[u8]| {
    for curve in [Curve::from_json(data), Curve::from_obj(data)]
        .into_iter()
        .flatten()
    {
        let again = Curve::from_json(curve.to_json().as_bytes());
        assert!(
            again.is_ok(),
            "a valid curve's JSON does not read back: {again:?}"
        );
    }
});
