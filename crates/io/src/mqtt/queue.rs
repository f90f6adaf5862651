//! The offline queue: outgoing messages waiting for the broker, bounded in
//! count and bytes. When full, the oldest message is dropped (a fresh location
//! is worth more than a stale one) and counted.

use std::collections::VecDeque;

use rumqttc::QoS;

/// One message ready for the wire.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Outgoing {
    pub topic: String,
    pub payload: Vec<u8>,
    pub qos: QoS,
    pub retain: bool,
}

impl Outgoing {
    /// What the message costs in the queue's byte bound.
    pub(crate) fn size(&self) -> usize {
        self.topic.len() + self.payload.len()
    }
}

#[derive(Debug)]
pub(crate) struct OfflineQueue {
    max_messages: usize,
    max_bytes: usize,
    items: VecDeque<Outgoing>,
    bytes: usize,
    dropped: u64,
}

impl OfflineQueue {
    pub(crate) fn new(max_messages: usize, max_bytes: usize) -> Self {
        OfflineQueue {
            max_messages: max_messages.max(1),
            max_bytes: max_bytes.max(1),
            items: VecDeque::new(),
            bytes: 0,
            dropped: 0,
        }
    }

    /// Appends a message, dropping the oldest ones past the bounds. A message
    /// larger than the whole byte bound is dropped itself.
    pub(crate) fn push(&mut self, message: Outgoing) {
        if message.size() > self.max_bytes {
            self.dropped += 1;
            return;
        }
        self.bytes += message.size();
        self.items.push_back(message);
        while self.items.len() > self.max_messages || self.bytes > self.max_bytes {
            self.pop();
            self.dropped += 1;
        }
    }

    /// Puts messages that were handed to the broker but not acknowledged back
    /// at the front, in their original order, within the same bounds (dropping
    /// from the front, the oldest).
    pub(crate) fn requeue_front(&mut self, messages: impl DoubleEndedIterator<Item = Outgoing>) {
        for message in messages.rev() {
            self.bytes += message.size();
            self.items.push_front(message);
        }
        while self.items.len() > self.max_messages || self.bytes > self.max_bytes {
            self.pop();
            self.dropped += 1;
        }
    }

    pub(crate) fn pop(&mut self) -> Option<Outgoing> {
        let message = self.items.pop_front()?;
        self.bytes -= message.size();
        Some(message)
    }

    pub(crate) fn len(&self) -> usize {
        self.items.len()
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    pub(crate) fn bytes(&self) -> usize {
        self.bytes
    }

    /// Messages dropped because the queue was full, since start.
    pub(crate) fn dropped(&self) -> u64 {
        self.dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(topic: &str, len: usize) -> Outgoing {
        Outgoing {
            topic: topic.into(),
            payload: vec![b'x'; len],
            qos: QoS::AtLeastOnce,
            retain: false,
        }
    }

    #[test]
    fn the_oldest_messages_go_first_when_the_count_is_exceeded() {
        let mut q = OfflineQueue::new(3, 1 << 20);
        for t in ["a", "b", "c", "d", "e"] {
            q.push(msg(t, 10));
        }
        assert_eq!(q.len(), 3);
        assert_eq!(q.dropped(), 2);
        let topics: Vec<_> = std::iter::from_fn(|| q.pop()).map(|m| m.topic).collect();
        assert_eq!(topics, ["c", "d", "e"]);
        assert_eq!(q.bytes(), 0);
    }

    #[test]
    fn the_byte_bound_holds_and_an_oversized_message_is_dropped() {
        let mut q = OfflineQueue::new(100, 50);
        q.push(msg("a", 20)); // 21 bytes
        q.push(msg("b", 20)); // 42
        q.push(msg("c", 20)); // 63 > 50: "a" goes
        assert_eq!((q.len(), q.bytes(), q.dropped()), (2, 42, 1));
        q.push(msg("huge", 100));
        assert_eq!((q.len(), q.dropped()), (2, 2));
    }

    #[test]
    fn requeued_messages_come_back_first_in_order() {
        let mut q = OfflineQueue::new(10, 1000);
        q.push(msg("c", 1));
        q.requeue_front([msg("a", 1), msg("b", 1)].into_iter());
        let topics: Vec<_> = std::iter::from_fn(|| q.pop()).map(|m| m.topic).collect();
        assert_eq!(topics, ["a", "b", "c"]);
    }
}
