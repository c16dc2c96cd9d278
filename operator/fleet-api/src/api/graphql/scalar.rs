//! `BigInt`, the scalar of the schema's 64-bit integers (`seq`, `tsMs`): GraphQL's `Int` holds
//! 32 bits, and Unix milliseconds (about 1.8 × 10¹²) overflow it in typed clients. A `BigInt`
//! is written as a string of decimal digits, as GitHub's GraphQL API writes its own, which
//! JavaScript also reads exactly beyond 2⁵³.

use async_graphql::{InputValueError, InputValueResult, Scalar, ScalarType, Value};

/// A 64-bit integer (signed or not).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BigInt(i128);

impl From<i64> for BigInt {
    fn from(n: i64) -> Self {
        Self(n.into())
    }
}

impl From<u64> for BigInt {
    fn from(n: u64) -> Self {
        Self(n.into())
    }
}

/// A 64-bit integer written as a string of decimal digits, e.g. "1796112000123" (GraphQL's Int
/// holds 32 bits): `seq`, and `tsMs`, Unix time in milliseconds. As an argument, a string or a
/// number.
#[Scalar(name = "BigInt")]
impl ScalarType for BigInt {
    fn parse(value: Value) -> InputValueResult<Self> {
        let parsed = match &value {
            Value::String(s) => s.trim().parse().ok(),
            Value::Number(n) => n.as_i64().map(i128::from),
            _ => None,
        };
        parsed
            .map(BigInt)
            .ok_or_else(|| InputValueError::expected_type(value))
    }

    fn is_valid(value: &Value) -> bool {
        matches!(value, Value::String(_) | Value::Number(_))
    }

    fn to_value(&self) -> Value {
        Value::String(self.0.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_big_int_is_a_string_of_digits_both_ways() {
        let now = BigInt::from(1_796_112_000_123_i64);
        assert_eq!(now.to_value(), Value::String("1796112000123".into()));
        let largest = BigInt::from(u64::MAX);
        assert_eq!(largest.to_value(), Value::String(u64::MAX.to_string()));
        assert_eq!(
            BigInt::from(i64::MIN).to_value(),
            Value::String(i64::MIN.to_string())
        );
        for input in [
            Value::String("1796112000123".into()),
            Value::from(1_796_112_000_123_i64),
        ] {
            assert_eq!(BigInt::parse(input).unwrap(), now);
        }
        assert!(BigInt::parse(Value::String("soon".into())).is_err());
    }
}
